"""Conditional density estimators: context encoders, flow backends, the combined estimator."""
