"""The real samples' fetch (tests/samples.py): a mirror over HTTP or in a folder, checksums, the
offline line, and the cache being reused. Each test serves a few of the manifest's real files."""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import shutil
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
import samples
from conftest import free_port

#: three of the manifest's files, one per kind (a table, a map raster's transform, a lidar frame)
NAMES = (
    "calibration/egovehicle_SE3_sensor.feather",
    "7fab2350-7eaf-3b7e-a39d-6937a4c1bede___img_Sim2_city.json",
    "000072.pcd",
)
NO_LOCAL = {"av2-sample": [], "opv2v-agent-sample": []}


@pytest.fixture(scope="module")
def files() -> list[samples.SampleFile]:
    chosen = [f for f in samples.manifest()[1] if f.path.endswith(NAMES)]
    assert len(chosen) == len(NAMES)
    return chosen


@pytest.fixture
def mirror(tmp_path, files) -> Path:
    """A mirror folder (``<sample>/<path>``) holding ``files``, copied from the tests' cache."""
    cache = samples.ensure()
    for f in files:
        target = tmp_path / "mirror" / f.sample / f.path
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(cache[f.sample] / f.path, target)
    return tmp_path / "mirror"


class Server:
    """``folder`` over HTTP on 127.0.0.1; ``paths``: every path asked for, in order."""

    def __init__(self, folder: Path):
        self.paths: list[str] = []
        server = self

        class Handler(SimpleHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 (http.server's name)
                server.paths.append(self.path)
                super().do_GET()

            def log_message(self, *args):
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=str(folder)))
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        threading.Thread(target=self.httpd.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def served(mirror):
    server = Server(mirror)
    yield server
    server.close()


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_an_http_mirror_fills_an_empty_cache_once_and_the_cache_is_reused(tmp_path, files, served):
    folders = samples.ensure(files, tmp_path / "cache", local=NO_LOCAL, mirror=served.url, origin=False)
    for f in files:
        assert sha256(folders[f.sample] / f.path) == f.sha256
    assert sorted(served.paths) == sorted(f"/{f.sample}/{f.path}" for f in files)
    samples.ensure(files, tmp_path / "cache", local=NO_LOCAL, mirror=served.url, origin=False)
    assert len(served.paths) == len(files)  # all from the cache: nothing asked again


def test_a_corrupted_mirror_file_is_discarded_and_named(tmp_path, files, mirror, served):
    bad = files[1]
    path = mirror / bad.sample / bad.path
    path.write_bytes(path.read_bytes().replace(b"1", b"2", 1))
    with pytest.raises(samples.SampleUnavailable) as raised:
        samples.ensure(files, tmp_path / "cache", local=NO_LOCAL, mirror=served.url, origin=False)
    line = str(raised.value)
    assert "\n" not in line and f"{bad.sample}/{bad.path}" in line and "checksum differs" in line
    assert samples.MIRROR_VARIABLE in line
    assert not (tmp_path / "cache" / bad.sample / bad.path).exists()
    left = {p.name for p in (tmp_path / "cache").rglob("*") if p.is_file() and p.name != ".lock"}
    assert left == {Path(files[0].path).name}  # the file before it, and no partial download


def test_a_file_whose_checksum_differs_falls_through_to_the_next_source(tmp_path, files, mirror, served):
    """A damaged local copy, then a damaged mirror file: the origin (a second, good server) gives it."""
    good = Server(mirror)
    try:
        bad = files[0]
        local = tmp_path / "local" / bad.sample
        (local / bad.path).parent.mkdir(parents=True)
        (local / bad.path).write_bytes(b"not the sample")
        damaged = mirror.parent / "damaged"
        shutil.copytree(mirror, damaged)
        (damaged / bad.sample / bad.path).write_bytes(b"not the sample either")
        server = Server(damaged)
        with_origin = dataclasses.replace(bad, origin=f"{good.url}/{bad.sample}/{bad.path}")
        folders = samples.ensure(
            [with_origin], tmp_path / "cache", local={bad.sample: [local]}, mirror=server.url, origin=True
        )
        assert sha256(folders[bad.sample] / bad.path) == bad.sha256
        assert server.paths == [f"/{bad.sample}/{bad.path}"] and good.paths == [f"/{bad.sample}/{bad.path}"]
        server.close()
    finally:
        good.close()


def test_a_local_folder_mirror_and_a_local_sample_folder(tmp_path, files, mirror):
    folders = samples.ensure(files, tmp_path / "cache", local=NO_LOCAL, mirror=str(mirror), origin=False)
    assert all(sha256(folders[f.sample] / f.path) == f.sha256 for f in files)
    av2 = [f for f in files if f.sample == "av2-sample"]
    folders = samples.ensure(
        av2, tmp_path / "cache2", local={"av2-sample": [mirror / "av2-sample"]}, mirror="", origin=False
    )
    assert all(sha256(folders[f.sample] / f.path) == f.sha256 for f in av2)


def test_offline_is_one_line_naming_the_mirror_variable(tmp_path, files):
    """No mirror answers and the origin is unreachable: one line naming the file, the places tried
    (each host asked once: the first file's failure marks it down) and the variable to set."""
    closed = f"http://127.0.0.1:{free_port()}"
    offline = [dataclasses.replace(f, origin=f"{closed}/origin/{f.path}") for f in files]
    with pytest.raises(samples.SampleUnavailable) as raised:
        samples.ensure(offline, tmp_path / "cache", local=NO_LOCAL, mirror=closed, origin=True)
    line = str(raised.value)
    assert "\n" not in line and line.count("(unreachable)") == 2
    assert f"{files[0].sample}/{files[0].path}" in line and samples.MIRROR_VARIABLE in line
    with pytest.raises(samples.SampleUnavailable) as raised:
        samples.ensure(offline, tmp_path / "cache", local=NO_LOCAL, mirror="", origin=False)
    assert f"${samples.MIRROR_VARIABLE} (not set)" in str(raised.value)


def test_the_manifest_pins_every_file_the_tests_read():
    """Every file of the samples' cache folders is in the manifest with its size (nothing read unlisted),
    and every file has a public origin at one commit: av2-api's unit-test data for the AV2 log, the
    COHFF-Occupancy-Process repository's OPV2V example for the OPV2V agent."""
    meta, listed = samples.manifest()
    folders = samples.ensure()
    on_disk = {(name, p.relative_to(folder).as_posix()) for name, folder in folders.items() for p in folder.rglob("*")}
    assert {(f.sample, f.path) for f in listed} <= on_disk
    assert all((folders[f.sample] / f.path).stat().st_size == f.size for f in listed)
    origins = {f.origin.split("/tests/unit/test_data/sensor/")[0] for f in listed if f.sample == "av2-sample"}
    assert origins == {"https://raw.githubusercontent.com/argoverse/av2-api/b7321d1f71f6ce0ecdd151f4f2b648338c191edd"}
    opv2v = {f.origin.split("/data_example/")[0] for f in listed if f.sample == "opv2v-agent-sample"}
    assert opv2v == {
        "https://raw.githubusercontent.com/Studeas/COHFF-Occupancy-Process/c6f909d38cc6b494b7e177dc94191bc58e1a8e3c"
    }
    assert all(f.origin.endswith("/" + f.path) for f in listed)
    assert set(meta) == {"av2-sample", "opv2v-agent-sample"} and all(m["licence"] for m in meta.values())
