"""A test hook (tests/test_stop.py): with ``NCORE_CONVERT_SIGNAL_AT=<module>:<signum>`` in its
environment, a Python process started with this folder on ``PYTHONPATH`` sends itself the signal at
the moment ``<module>`` starts importing (from a meta-path finder, before the module's code runs),
so a stop arrives mid-import every time, not by timing luck. The variable is removed at start-up:
the processes the run starts do not signal themselves."""

import os
import sys

_WHEN = os.environ.pop("NCORE_CONVERT_SIGNAL_AT", "")


class _SignalAtImport:
    def __init__(self, module: str, signum: int) -> None:
        self.module, self.signum = module, signum

    def find_spec(self, name, path=None, target=None):
        if name == self.module:
            sys.meta_path.remove(self)
            os.write(2, f"[signal-at-import: {self.module}]\n".encode())
            os.kill(os.getpid(), self.signum)
        return None  # the module's own finders import it


if _WHEN:
    _module, _signum = _WHEN.rsplit(":", 1)
    sys.meta_path.insert(0, _SignalAtImport(_module, int(_signum)))
