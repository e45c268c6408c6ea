"""Errors whose message is meant for the user as is (the CLI prints it on one line and exits with 2).

Every input the user controls (scenario files, the files they name, model and dataset files,
command-line values) is refused with an :class:`InputError` whose message names the file and
the field or line and what was expected. Nothing is written before such an input is checked.
"""


class InputError(ValueError):
    """An input the user controls that cannot be used; the message names it and what was expected."""


class UsageError(InputError):
    """A bad command-line argument; the message names the option and what was expected."""


class ScenarioError(InputError):
    """A scenario file (or a file it names) that cannot be used. The message is meant for the user as is."""
