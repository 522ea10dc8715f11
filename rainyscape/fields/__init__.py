"""fields components."""
