"""Errors a user can cause (bad paths, inconsistent data, impossible options).

The CLI prints these as one clear message and exits non-zero, without a traceback.
Everything else that escapes is a bug in cogs and keeps its traceback.
"""


class UserError(Exception):
    """A problem with the user's input, named precisely enough to fix it."""
