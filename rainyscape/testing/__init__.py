"""Test and benchmark helpers: synthetic inputs with known answers and slow reference
implementations that the fast code is checked against. Nothing in the package imports it."""
