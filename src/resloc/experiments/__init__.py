"""Experiments: scenarios, metrics, runs, sweeps and reports."""
