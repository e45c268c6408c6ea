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


class JobError(RuntimeError):
    """Work handed to a worker process failed: its task raised, or the worker died. The message
    names the work and gives the first line of the cause; the CLI prints it and exits with 1, as
    for the same failure in the parent process."""

    def __init__(self, what: str, cause: str):
        super().__init__(f"{what} failed: {cause.splitlines()[0] if cause else 'no cause given'}")
        self.details = cause
