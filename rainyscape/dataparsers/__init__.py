"""dataparsers components."""
