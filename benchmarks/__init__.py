"""Measurements that print figures and write JSON under ``benchmarks/results/``; each runs as a
module from the repository root (``python -m benchmarks.evaluate``). Nothing imports them but
themselves and the tests."""
