"""The one exception the command line turns into a single line and exit status 2."""

from __future__ import annotations


class InputError(ValueError):
    """Bad input from the user: its message names what is wrong and what is expected."""
