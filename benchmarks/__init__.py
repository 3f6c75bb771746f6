"""Benchmarks of the tuner daemon (``pitune bench``); results in ``benchmarks/results/``."""
