"""postprocess components."""
