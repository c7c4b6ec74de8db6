"""Weekly forecasts of I and reported cases: members, ensemble, recalibration, real-time backtest."""
