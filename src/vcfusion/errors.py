"""Errors whose message is meant for the user as is (the CLI prints it and exits with 2)."""


class UsageError(ValueError):
    """A bad command-line argument; the message names the option and what was expected."""
