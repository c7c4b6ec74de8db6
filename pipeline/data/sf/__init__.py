"""San Francisco's daily cases, deaths and tests from DataSF, and their S/I/R conversion."""
