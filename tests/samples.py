"""The real samples the tests read, fetched once into a cache and checked byte for byte.

``tests/samples.toml`` lists every file: its sample folder, path, SHA-256, size and public origin.
:func:`ensure` puts each file into the cache (``$NCORE_CONVERT_SAMPLES_CACHE``, else the platform's
user cache: ``pooch.os_cache``) from the first source whose bytes match (see the manifest's header
for the order), and the tests read the cache. A file that no source can give stops the run with
one line (:class:`SampleUnavailable`). Downloads go through pooch with explicit connect and read
timeouts, and a host that does not answer once is not asked again in the same call, so an offline
machine is told within seconds.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import tomllib
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

import pooch
import requests
from filelock import FileLock

REPO = Path(__file__).resolve().parents[1]
MANIFEST = Path(__file__).with_name("samples.toml")
MIRROR_VARIABLE = "NCORE_CONVERT_SAMPLES_MIRROR"
CACHE_VARIABLE = "NCORE_CONVERT_SAMPLES_CACHE"
TIMEOUT_S = (5.0, 30.0)  #: (connect, read) for each download


class SampleUnavailable(RuntimeError):
    """No source gave a sample file with the manifest's checksum (the message is one line)."""


@dataclass(frozen=True)
class SampleFile:
    sample: str  #: the sample folder: ``av2-sample`` or ``opv2v-lidar-sample``
    path: str  #: the file inside that folder, ``/``-separated
    sha256: str
    size: int
    origin: str  #: its public URL ("" when none is known)


def manifest(path: Path = MANIFEST) -> tuple[dict[str, dict], list[SampleFile]]:
    """The manifest's samples (name -> ``variable``, ``licence``, ``about``) and files."""
    data = tomllib.loads(path.read_text())
    return data["samples"], [SampleFile(**f) for f in data["files"]]


def cache_dir() -> Path:
    return Path(os.environ.get(CACHE_VARIABLE) or pooch.os_cache("ncore-convert")) / "samples"


def shared_data_roots() -> list[Path]:
    """``../shared/data`` beside the repository, and beside its parent (a clone under a work folder)."""
    return [REPO.parent / "shared" / "data", REPO.parent.parent / "shared" / "data"]


def _matches(path: Path, file: SampleFile) -> bool:
    return path.is_file() and path.stat().st_size == file.size and pooch.file_hash(str(path)) == file.sha256


def _copy_in(source: Path, target: Path) -> None:
    """``source`` to ``target`` through a temporary file beside it (a reader never sees half a file)."""
    with tempfile.NamedTemporaryFile(dir=target.parent, delete=False) as tmp:
        shutil.copyfileobj(source.open("rb"), tmp)
    os.replace(tmp.name, target)


class _Fetcher:
    """One :func:`ensure` call's downloads: the hosts that did not answer are not asked again."""

    def __init__(self) -> None:
        self.down: set[str] = set()
        self.downloader = pooch.HTTPDownloader(progressbar=False, timeout=TIMEOUT_S)

    def get(self, url: str, file: SampleFile, target: Path) -> str | None:
        """Download ``url`` to ``target`` if its bytes match ``file``; else why not."""
        host = urlsplit(url).netloc
        if host in self.down:
            return "unreachable"
        try:
            pooch.retrieve(
                url, "sha256:" + file.sha256, target.name, target.parent, downloader=self.downloader, progressbar=False
            )
            return None
        except ValueError:
            return "checksum differs"
        except requests.HTTPError as error:
            return f"HTTP {error.response.status_code}"
        except (requests.ConnectionError, requests.Timeout):
            self.down.add(host)
            return "unreachable"


def ensure(
    files: list[SampleFile] | None = None,
    cache: Path | None = None,
    *,
    local: dict[str, list[Path]] | None = None,
    mirror: str | None = None,
    origin: bool = True,
) -> dict[str, Path]:
    """Every sample file in the cache with the manifest's checksum; returns sample -> its cache folder.

    ``local``: sample -> the sample folders tried first (default: the sample's variable, then
    ``<shared data root>/<sample>``); ``mirror``: a base URL or folder (default
    ``$NCORE_CONVERT_SAMPLES_MIRROR``); ``origin``: try the public origins last. Raises
    :class:`SampleUnavailable` naming the first file no source could give, the places tried and the
    variable to set. Safe under concurrent callers (pytest-xdist workers): a file lock in the cache.
    """
    samples, listed = manifest()
    files = listed if files is None else files
    cache = cache or cache_dir()
    mirror = os.environ.get(MIRROR_VARIABLE, "") if mirror is None else mirror
    cache.mkdir(parents=True, exist_ok=True)
    pooch.get_logger().setLevel("WARNING")
    fetcher = _Fetcher()
    with FileLock(str(cache / ".lock")):
        for file in files:
            target = cache / file.sample / file.path
            if _matches(target, file):
                continue
            target.unlink(missing_ok=True)
            target.parent.mkdir(parents=True, exist_ok=True)
            folders = local[file.sample] if local is not None else _local_folders(file.sample, samples)
            sources, missing = _sources(file, folders, mirror, origin)
            tried = _obtain(file, target, sources, fetcher)
            if tried is not None:
                tried += missing
                variable, places = samples[file.sample]["variable"], "; ".join(tried) or "nothing"
                raise SampleUnavailable(
                    f"real sample file {file.sample}/{file.path} could not be obtained; tried: {places}."
                    f" Set {MIRROR_VARIABLE} to a URL or folder holding {file.sample}/{file.path}"
                    f" (or {variable} to the sample's folder); see docs/tests.md"
                )
    return {name: cache / name for name in samples}


def _local_folders(name: str, samples: dict[str, dict]) -> list[Path]:
    """The folders tried first for a sample: its variable's folder (if set), then the shared roots'."""
    own = os.environ.get(samples[name]["variable"])
    return ([Path(own)] if own else []) + [root / name for root in shared_data_roots()]


def _sources(file: SampleFile, folders: list[Path], mirror: str, origin: bool) -> tuple[list[Path | str], list[str]]:
    """Where ``file`` may come from, in order (local paths, then URLs), and the sources not available."""
    sources: list[Path | str] = [folder / file.path for folder in folders]
    missing = []
    if mirror.startswith(("http://", "https://")):
        sources.append(f"{mirror.rstrip('/')}/{file.sample}/{file.path}")
    elif mirror:
        sources.append(Path(mirror) / file.sample / file.path)
    else:
        missing.append(f"${MIRROR_VARIABLE} (not set)")
    if origin and file.origin:
        sources.append(file.origin)
    elif origin:
        missing.append("a public origin (none known)")
    return sources, missing


def _obtain(file: SampleFile, target: Path, sources: list[Path | str], fetcher: _Fetcher) -> list[str] | None:
    """``file`` into ``target`` from the first source that has its bytes: None then, else what was tried."""
    tried = []
    for source in sources:
        if isinstance(source, Path):
            if _matches(source, file):
                _copy_in(source, target)
                return None
            why = "checksum differs" if source.exists() else "absent"
        else:
            why = fetcher.get(source, file, target)
            if why is None:
                return None
        tried.append(f"{source} ({why})")
    return tried
