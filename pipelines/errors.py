"""The exceptions the command line turns into a single line: bad input (exit status 2), a diverged run (1)."""

from __future__ import annotations


class InputError(ValueError):
    """Bad input from the user: its message names what is wrong and what is expected."""


class TrainingDiverged(RuntimeError):
    """A loss or parameter became NaN or infinite; the run stopped, its last checkpoint is the last finite state."""
