"""How the input is opened: the dataset root as an fsspec path (anonymous when asked), and the one
line that names a credential problem.

- ``--anonymous`` reads the input without credentials: s3fs's ``anon=True`` (gcsfs: ``token="anon"``).
  It applies to the input only (``--root-dir``, ``validate --source``); the output is always
  written with the caller's credentials. The option lives in the root path's storage options, so
  it reaches the workers and Ray tasks with the path, and stays out of the conversion's
  fingerprint (the dataset options).
- S3 input gets a connection pool as large as the reader's read-ahead (``reader.MAX_AHEAD``; aiobotocore
  allows 10 connections by default), so files fetched ahead are in flight together.
- :func:`access_problem` turns the errors of a missing, refused or expired credential into one
  line naming the fix: no credentials (name ``--anonymous``), invalid or expired credentials, a
  private bucket read anonymously, and an instance metadata service that did not answer.
"""

from __future__ import annotations

import os
import socket
import urllib.error
import urllib.request

from upath import UPath

from ncore_convert.paths import is_local
from ncore_convert.sources.reader import MAX_AHEAD

#: error codes of credentials the store does not accept
INVALID_CODES = {
    "InvalidAccessKeyId",
    "SignatureDoesNotMatch",
    "ExpiredToken",
    "ExpiredTokenException",
    "InvalidToken",
    "TokenRefreshRequired",
    "InvalidClientTokenId",
}
METADATA_PROBE_S = 1.0  #: how long the metadata service may take to answer


def input_root(url: str, anonymous: bool = False) -> UPath:
    """The dataset root (local path or fsspec URL); ``anonymous``: read without credentials
    (ValueError for a store that has no anonymous mode here)."""
    path = UPath(url)
    if is_local(path):
        return path
    if path.protocol in ("s3", "s3a"):
        return UPath(url, anon=anonymous, config_kwargs={"max_pool_connections": MAX_AHEAD})
    if anonymous and path.protocol in ("gs", "gcs"):
        return UPath(url, token="anon")
    if anonymous:
        raise ValueError(f"--anonymous: no anonymous mode known for {path.protocol}:// input")
    return path


def _error_code(err: BaseException) -> str | None:
    for e in (err, err.__cause__, err.__context__):
        response = getattr(e, "response", None)
        if isinstance(response, dict):
            return response.get("Error", {}).get("Code")
    return None


def _metadata_service_silent() -> str | None:
    """The instance metadata service's address if it does not answer a token request within
    METADATA_PROBE_S (botocore then finds no credentials and says only that), else None."""
    if os.environ.get("AWS_EC2_METADATA_DISABLED", "").lower() == "true":
        return None
    endpoint = os.environ.get("AWS_EC2_METADATA_SERVICE_ENDPOINT", "http://169.254.169.254/")
    request = urllib.request.Request(
        endpoint.rstrip("/") + "/latest/api/token", method="PUT", headers={"X-aws-ec2-metadata-token-ttl-seconds": "60"}
    )
    try:
        urllib.request.urlopen(request, timeout=METADATA_PROBE_S).close()
    except urllib.error.HTTPError:
        return None  # it answered
    except TimeoutError:
        return endpoint
    except urllib.error.URLError as err:
        return endpoint if isinstance(err.reason, TimeoutError | socket.timeout) else None
    except OSError:
        return None
    return None


def access_problem(err: BaseException, what: str, anonymous: bool) -> str | None:
    """One line for a credential problem met while reading ``what`` (``--root-dir s3://...``), or
    None when ``err`` is not one."""
    names = {type(e).__name__ for e in (err, err.__cause__, err.__context__) if e is not None}
    code = _error_code(err)
    if names & {"NoCredentialsError", "PartialCredentialsError"}:
        silent = _metadata_service_silent()
        where = (
            f"; the instance metadata service ({silent}) did not answer within {METADATA_PROBE_S:g} s" if silent else ""
        )
        return f"{what}: no credentials found{where}; for a public bucket add --anonymous (before the command)"
    if names & {"CredentialRetrievalError", "MetadataRetrievalError"}:
        return f"{what}: credentials could not be retrieved ({err}); set them, or add --anonymous for a public bucket"
    if code in INVALID_CODES:
        return f"{what}: the credentials were refused ({code}: invalid or expired); renew them"
    if code in ("AccessDenied", "AllAccessDisabled", "403") or isinstance(err, PermissionError):
        if anonymous:
            return f"{what}: access denied to an anonymous reader (not a public bucket); drop --anonymous"
        return f"{what}: access denied ({code or err}); check the credentials' permissions"
    return None
