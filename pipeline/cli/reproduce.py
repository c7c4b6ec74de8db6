"""`flowcast reproduce` commands (being written)."""
