"""`flowcast data` commands (being written)."""
