"""The weekly San Francisco forecast as a typed library (the Prefect flow only wraps it).

- :mod:`~pipeline.forecast.config` — :class:`ForecastConfig`, the data source, the presets;
- :mod:`~pipeline.forecast.settings` — the settings of each step (its sub-configs);
- :mod:`~pipeline.forecast.sources` — step 1, the DataSF series and its S/I/R proportions;
- :mod:`~pipeline.forecast.joint_models` — steps 2–3, training data and the joint estimators;
- :mod:`~pipeline.forecast.steps` — steps 4–8, estimates, rollouts, β/γ, NLL, SMC;
- :mod:`~pipeline.forecast.published_forecast` — step 9, the published forecast and its
  track record;
- :mod:`~pipeline.forecast.results` — the typed outputs, :class:`ForecastResults`;
- :mod:`~pipeline.forecast.run` — :func:`run_forecast`, the one composition of the steps;
- :mod:`~pipeline.forecast.publish` — the run's files, staged and promoted.
"""
from pipeline.forecast.config import (FORECAST_PRESETS, DataSourceConfig, ForecastConfig,
                                      resolve_config)
from pipeline.forecast.results import ForecastResults
from pipeline.forecast.run import StepRunner, run_forecast

__all__ = ["FORECAST_PRESETS", "DataSourceConfig", "ForecastConfig", "ForecastResults",
           "StepRunner", "resolve_config", "run_forecast"]
