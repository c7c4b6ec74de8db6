"""The one real-time backtest, its results and writers, a place's track record and its memo."""
