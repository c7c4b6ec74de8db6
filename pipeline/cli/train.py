"""`flowcast train` commands (being written)."""
