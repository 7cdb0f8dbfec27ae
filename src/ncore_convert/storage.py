"""Output-storage helpers shared by the writer and the runner: durability and removal.

Local paths are flushed with fsync, so a sequence is on disk before its folder is renamed into
place; object stores (s3://, gs://, ...) make an object durable when it is closed.
"""

from __future__ import annotations

import os
import shutil

from upath import UPath


def is_local(path: UPath) -> bool:
    return path.protocol in ("", "file", "local")


def flush_to_disk(path: UPath) -> None:
    """fsync a local file, or every file and folder of a local tree (no-op for object stores)."""
    if not is_local(path):
        return
    if os.path.isdir(path.path):
        for folder, _, files in os.walk(path.path):
            for name in files:
                _fsync(os.path.join(folder, name), os.O_RDONLY)
            _fsync(folder, os.O_RDONLY | os.O_DIRECTORY)
    else:
        _fsync(path.path, os.O_RDONLY)


def _fsync(path: str, flags: int) -> None:
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def remove_tree(path: UPath) -> None:
    """Delete a file tree, local or remote, if it exists."""
    if path.exists():
        if is_local(path):
            shutil.rmtree(path.path)
        else:
            path.fs.rm(path.path, recursive=True)
