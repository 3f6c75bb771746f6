"""pitune: online PI tuning with a meta-reinforcement-learning agent."""

__version__ = "0.1.0"


class UsageError(ValueError):
    """Input a user gave a command (a flag's value, a file it names) that the command
    refuses: ``pitune`` prints the message as one line and exits 2, as for a bad command
    line; called as a library, an ordinary ValueError."""
