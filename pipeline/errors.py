"""User-facing errors.

A `UserError` is raised for a mistake the user can fix (a missing file, a corrupt dataset, a bad
param). The CLI prints its message on one line and exits non-zero, without a traceback. Messages say
what is wrong, where (file, key, episode), and what to do about it.
"""


class UserError(Exception):
    """A problem with the user's input, reported as one line by the CLI."""
