"""The CDC COVID-19 Forecast Hub's data: its locations, NHSN admissions and NSSP ED shares as
vintages (live or imported from a hub's target data), and other teams' forecasts."""
