"""`flowcast smc` commands (being written)."""
