"""process components."""
