from pipeline.forecast.steps import *  # noqa: F401,F403  (temporary during the split)
