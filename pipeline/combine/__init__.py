"""Combining the members: averages, weights, recalibration, sample paths — one combiner."""
