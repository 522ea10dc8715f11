"""Evaluation: metrics, the evaluation protocol, renders and reports."""
