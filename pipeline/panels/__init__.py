"""Panels: the places forecast together, their histories as known at an origin, the targets."""
