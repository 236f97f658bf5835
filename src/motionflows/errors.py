"""Project exception types. Each message names the problem and the fix."""

from __future__ import annotations


class MotionflowsError(Exception):
    """Base class of motionflows' own errors."""


class MotionDataError(MotionflowsError, ValueError):
    """A motion file or dataset is missing, malformed or inconsistent.

    Raised with the file (and line, where there is one) and what to do about it.
    """

    def __init__(self, message: str, *, path: str | None = None, line: int | None = None):
        where = ""
        if path is not None:
            where = f"{path}:{line}: " if line is not None else f"{path}: "
        super().__init__(where + message)
        self.path = path
        self.line = line


class RunError(MotionflowsError, ValueError):
    """A run directory, experiment name or CLI argument is unusable."""
