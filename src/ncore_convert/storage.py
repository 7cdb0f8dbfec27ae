"""Output-storage helpers shared by the writer and the runner: durability, removal, publishing.

Local paths are flushed with fsync, so a sequence is on disk before its folder is renamed into
place; object stores (s3://, gs://, ...) make an object durable when it is closed.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import threading
from pathlib import Path

from upath import UPath

from ncore_convert.paths import is_local


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


def precondition_failed(err: Exception) -> bool:
    """An object store refused a conditional write (HTTP 412 or 409; s3fs raises FileExistsError for
    a refused create and an OSError caused by the client's error otherwise)."""
    if isinstance(err, FileExistsError):
        return True
    response = getattr(err.__cause__, "response", None) or {}
    code = response.get("Error", {}).get("Code")
    status = response.get("ResponseMetadata", {}).get("HTTPStatusCode")
    return code in ("PreconditionFailed", "ConditionalRequestConflict") or status in (409, 412)


def remove_tree(path: UPath) -> None:
    """Delete a file tree, local or remote, if it exists."""
    if path.exists():
        if is_local(path):
            shutil.rmtree(path.path)
        else:
            path.fs.rm(path.path, recursive=True)


def publish(work: UPath, final: UPath, flushed: bool = False) -> None:
    """Move a finished sequence folder into place, replacing any previous ``final``.

    Local: flushed to disk (unless the caller did, ``flushed``), then renamed (atomic within one
    file system). Object store (``work`` is a local staging folder): every data object is uploaded
    (concurrently), and only once all are complete, the folder's top-level JSON files (the
    sequence meta ``<log_id>.json`` that readers open first): a reader never finds the JSON before
    the stores it names. An upload that fails removes what it wrote (s3fs aborts a multipart
    upload that fails). Either way ``final`` never looks complete before it is.
    """
    remove_tree(final)
    if is_local(final):
        if not flushed:
            flush_to_disk(work)
        work.rename(final)
        _fsync(final.parent.path, os.O_RDONLY | os.O_DIRECTORY)  # the rename itself (not the siblings)
        return
    _uploading.add(final)
    try:
        _upload(work, final)
    finally:
        _uploading.discard(final)


#: files uploaded at once: s3fs reads a file under 100 MB whole into memory before its PUT, so this
#: bounds what an upload holds (the 4 s log's output to a bucket: 1.1 GB peak unbounded, 582 MB at 4,
#: 461 MB at 2, and no slower)
UPLOAD_CONCURRENCY = 2
#: the remote sequence folders this process is uploading (a stop aborts their multipart uploads)
_uploading: set[UPath] = set()


def _upload(work: UPath, final: UPath) -> None:
    files = sorted(p for p in Path(work.path).rglob("*") if p.is_file())
    last = [p for p in files if p.parent == Path(work.path) and p.suffix == ".json"]
    first = [p for p in files if p not in last]
    try:
        for batch in (first, last):
            if batch:
                local, remote = [str(p) for p in batch], [_remote(final, work, p) for p in batch]
                final.fs.put(local, remote, batch_size=UPLOAD_CONCURRENCY)
    except BaseException:
        remove_tree(final)
        raise


def _remote(final: UPath, work: UPath, local_file: Path) -> str:
    return f"{final.path}/{local_file.relative_to(work.path).as_posix()}"


def abort_uploads(final: UPath) -> int:
    """Abort the unfinished multipart uploads under a remote sequence folder (the run holds the
    log's claim, so they are its own); the number aborted. Stores without multipart uploads: 0."""
    fs = final.fs
    if is_local(final) or not hasattr(fs, "call_s3"):
        return 0
    bucket, prefix, _ = fs.split_path(final.path)
    listed = fs.call_s3("list_multipart_uploads", Bucket=bucket, Prefix=prefix.rstrip("/") + "/")
    uploads = listed.get("Uploads", [])
    for upload in uploads:
        fs.call_s3("abort_multipart_upload", Bucket=bucket, Key=upload["Key"], UploadId=upload["UploadId"])
    return len(uploads)


def abort_uploads_in_flight(timeout_s: float = 3.0) -> None:
    """For a stop that ends the process at once: abort the multipart uploads of the sequences this
    process is uploading, within ``timeout_s`` (an upload's parts stay invisible either way)."""
    folders = list(_uploading)
    if not folders:
        return

    def abort() -> None:
        for final in folders:
            with contextlib.suppress(Exception):
                abort_uploads(final)

    worker = threading.Thread(target=abort, daemon=True)
    worker.start()
    worker.join(timeout_s)
