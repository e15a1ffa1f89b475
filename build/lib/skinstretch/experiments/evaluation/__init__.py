"""Evaluation of results against a simulated session's ground truth: one module per part of the JSON report."""
