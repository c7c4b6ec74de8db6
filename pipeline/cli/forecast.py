"""`flowcast forecast` commands (being written)."""
