"""The nowcast of data still being reported, and forecasting from its completions."""
