"""`flowcast demo` commands (being written)."""
