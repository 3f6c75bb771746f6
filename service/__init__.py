"""pitune: online PI tuning with a meta-reinforcement-learning agent."""

__version__ = "0.1.0"
