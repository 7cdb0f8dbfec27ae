"""Where a path lives: the one test of local against object storage, shared by the input side
(``sources/``) and the output side (``storage``, ``run/``)."""

from __future__ import annotations

from upath import UPath


def is_local(path: UPath) -> bool:
    """Whether ``path`` is on this machine's file system (not s3://, gs://, ...)."""
    return path.protocol in ("", "file", "local")
