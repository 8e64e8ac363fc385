"""Benchmarks: `python -m bench all` regenerates docs/benchmarks.md from each stage's results."""
