"""Conditional masked autoregressive flow backends behind one interface."""
