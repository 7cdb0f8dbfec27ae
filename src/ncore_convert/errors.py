"""The two failures the runner tells apart from bugs: bad input, and a conversion that failed its checks.

Both survive pickling from a worker process with their fields intact, so a log converted in a worker
or on a Ray node is reported exactly as one converted in the main process.
"""

from __future__ import annotations


class SourceError(Exception):
    """Bad or missing source input. ``str(err)`` is one line: ``<file>: <cause>``."""

    def __init__(self, path: object, cause: str) -> None:
        super().__init__(f"{path}: {cause}")
        self.path = str(path)
        self.cause = cause

    def __reduce__(self):  # keep (path, cause) when raised in a worker process
        return SourceError, (self.path, self.cause)


class ValidationFailed(Exception):
    """A converted log failed validation; ``validation`` is its ``validate.report.summarise`` record."""

    def __init__(self, message: str, validation: dict) -> None:
        super().__init__(message, validation)  # both in args: survives pickling from a worker
        self.validation = validation

    def __str__(self) -> str:
        return self.args[0]


class UsageError(Exception):
    """An option that cannot apply to this log (e.g. a clip window outside it): the command line is
    wrong, not the data. ``str(err)`` is one line naming the log and the cause."""

    def __reduce__(self):
        return UsageError, self.args
