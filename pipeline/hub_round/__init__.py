"""A round of the CDC COVID-19 Forecast Hub as a typed library run (``run``) and its files
(``publish``); the Prefect flow ``flows/hub_forecast.py`` runs the two as tasks."""
