"""Real San Francisco COVID-19 data: DataSF client, CSV import, validation, cache, S/I/R conversion."""
