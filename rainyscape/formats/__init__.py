"""File formats written and read in more than one layer (bottom layer: numpy and errors only)."""
