"""`flowcast estimate` commands (being written)."""
