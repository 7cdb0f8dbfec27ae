"""The two failures the runner tells apart from bugs: bad input, and a conversion that failed its checks.

Both survive pickling from a worker process with their fields intact, so a log converted in a worker
or on a Ray node is reported exactly as one converted in the main process.
"""

from __future__ import annotations

import contextlib


class SourceError(Exception):
    """Bad or missing source input. ``str(err)`` is one line: ``<file>: <cause>``."""

    def __init__(self, path: object, cause: str) -> None:
        super().__init__(f"{path}: {cause}")
        self.path = str(path)
        self.cause = cause

    def __reduce__(self):  # keep (path, cause) and the warnings when raised in a worker process
        return SourceError, (self.path, self.cause), self.__dict__


class ValidationFailed(Exception):
    """A converted log failed validation; ``validation`` is its ``validate.report.summarise`` record."""

    def __init__(self, message: str, validation: dict, log_warnings: list[str] = ()) -> None:
        super().__init__(message, validation, list(log_warnings))  # in args: survives pickling from a worker
        self.validation = validation
        self.log_warnings = list(log_warnings)  #: the converted log's warnings (see warnings_kept)

    def __str__(self) -> str:
        return self.args[0]


class UsageError(Exception):
    """An option that cannot apply to this log (e.g. a clip window outside it): the command line is
    wrong, not the data. ``str(err)`` is one line naming the log and the cause."""

    def __reduce__(self):
        return UsageError, self.args, self.__dict__


@contextlib.contextmanager
def warnings_kept(warnings: list[str]):
    """Any exception leaving the block carries ``warnings`` (the log's warnings so far) in its
    ``log_warnings``, ahead of those it carries already, so that a failed log's report keeps every
    warning. The attribute survives pickling from a worker process."""
    try:
        yield
    except Exception as err:
        err.log_warnings = list(dict.fromkeys([*warnings, *getattr(err, "log_warnings", [])]))
        raise
