"""Offline learning: the training environment, the oracle, training and evaluation."""
