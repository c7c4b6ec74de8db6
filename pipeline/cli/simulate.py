"""`flowcast simulate` commands (being written)."""
