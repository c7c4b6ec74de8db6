"""Small self-contained demonstrations (e.g. the kinetic-energy double-moon figure)."""
