"""methods components."""
