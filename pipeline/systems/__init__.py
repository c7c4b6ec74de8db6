"""Simulated dynamical systems: the SIR epidemic model and the switching autonomous vehicle."""
