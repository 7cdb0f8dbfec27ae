"""Reading the input from a bucket (``sources/reader.py``, ``sources/access.py``): one GET per
object and no HEAD, every byte once, anonymous input, one line per credential problem, and a
conversion through a proxy that refuses and drops requests. A moto S3 server behind
``tests/latency_proxy.py`` (no delay: the counts do not depend on it) stands for the bucket."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import pytest
from conftest import av2_args, av2_command, run_cli
from latency_proxy import LatencyProxy
from upath import UPath

from ncore_convert.synth.argoverse2 import SynthConfig, write_log

CREDENTIALS = ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN", "AWS_PROFILE")


def hashes(root: Path) -> dict[str, str]:
    """Every output file's SHA-256 by relative path (the run report aside: it holds wall times)."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != "conversion-report.json"
    }


def public_read(endpoint_url: str, bucket: str) -> None:
    """A bucket policy that lets anyone list the bucket and read its objects (a public dataset's)."""
    import botocore.session

    statements = [
        {"Effect": "Allow", "Principal": "*", "Action": "s3:ListBucket", "Resource": f"arn:aws:s3:::{bucket}"},
        {"Effect": "Allow", "Principal": "*", "Action": "s3:GetObject", "Resource": f"arn:aws:s3:::{bucket}/*"},
    ]
    client = botocore.session.get_session().create_client("s3", endpoint_url=endpoint_url)
    client.put_bucket_policy(Bucket=bucket, Policy=json.dumps({"Version": "2012-10-17", "Statement": statements}))


@pytest.fixture(scope="module")
def bucket_log(s3_env, tmp_path_factory):
    """A small synthetic AV2 log in a bucket (``s3://datasets/av2/val``), and its local conversion."""
    import s3fs

    tmp = tmp_path_factory.mktemp("objects")
    truth = write_log(UPath(tmp / "src" / "val"), SynthConfig(seconds=0.3, seed=43, camera_fps=5, camera_scale=4))
    fs = s3fs.S3FileSystem(skip_instance_cache=True)
    fs.mkdir("datasets")
    fs.put(str(tmp / "src" / "val") + "/", "datasets/av2/val/", recursive=True)
    public_read(s3_env["AWS_ENDPOINT_URL"], "datasets")
    files = {str(p.relative_to(tmp / "src")): p.stat().st_size for p in (tmp / "src").rglob("*") if p.is_file()}
    local = run_cli(*av2_args(tmp / "src", tmp / "local"))  # no bucket: in this process
    assert local.returncode == 0, local.stdout + local.stderr
    return truth, files, hashes(tmp / "local"), tmp


def convert_through(proxy: LatencyProxy, env: dict, out: str, *group_options: str) -> subprocess.CompletedProcess:
    env = {**env, "AWS_ENDPOINT_URL": proxy.url}
    command = av2_command("s3://datasets/av2", out, "--workers", "2", *group_options)
    return subprocess.run(command, capture_output=True, text=True, timeout=600, env=env)


def test_each_object_is_fetched_once_by_one_get_and_no_head(s3_env, bucket_log, tmp_path):
    """The default command from the bucket: one GET per object (the ego-mask sample, calibration,
    label and validation reads take the spooled copies), no HEAD, the source's bytes once, a few
    LISTs, and the local conversion's output."""
    _, files, local, _ = bucket_log
    with LatencyProxy(s3_env["AWS_ENDPOINT_URL"]) as proxy:
        run = convert_through(proxy, s3_env, str(tmp_path / "out"))
        assert run.returncode == 0, run.stdout + run.stderr
        gets = {path: n for (kind, path), n in proxy.keys.items() if kind == "GET"}
        assert proxy.counts["HEAD"] == 0, sorted(p for k, p in proxy.keys if k == "HEAD")[:5]
        assert sorted(gets) == sorted(f"/datasets/av2/{name}" for name in files)
        assert set(gets.values()) == {1}, sorted(p for p, n in gets.items() if n > 1)[:5]
        assert proxy.bytes_out == sum(files.values())
        folders = {str(Path(name).parent) for name in files}
        assert proxy.counts["LIST"] <= 2 * len(folders) + 6, proxy.counts
        assert proxy.counts["PUT"] == 0
    assert hashes(tmp_path / "out") == local


def test_a_flaky_bucket_converts_to_the_same_output(s3_env, bucket_log, tmp_path):
    """5 % of requests answered 503 SlowDown and 3 % of connections dropped (seeded; the bench runs
    the issue's 2 % and 1 % on a larger log), input from and output to the bucket: the retries carry
    the run, and the output is the local conversion's."""
    import s3fs

    _, _, local, _ = bucket_log
    with LatencyProxy(s3_env["AWS_ENDPOINT_URL"], slow_down=0.05, drop=0.03, seed=66) as proxy:
        run = convert_through(proxy, s3_env, "s3://converted/flaky")
        assert run.returncode == 0, run.stdout + run.stderr
        assert proxy.faults["503"] > 0 and proxy.faults["drop"] > 0, proxy.faults
    fs = s3fs.S3FileSystem(skip_instance_cache=True)
    fs.get("converted/flaky/", str(tmp_path / "got") + "/", recursive=True)
    assert hashes(tmp_path / "got") == local


def no_credentials(env: dict, **extra: str) -> dict:
    return {**{k: v for k, v in env.items() if k not in CREDENTIALS}, "AWS_EC2_METADATA_DISABLED": "true", **extra}


def one_line_error(run: subprocess.CompletedProcess) -> str:
    """The run's error line; the run must exit 2 with that one line and no traceback."""
    lines = [line for line in (run.stdout + run.stderr).splitlines() if line.strip()]
    assert run.returncode == 2 and len(lines) == 1 and "Traceback" not in run.stderr, run.stdout + run.stderr
    return lines[0]


def test_anonymous_input_converts_without_any_credentials(s3_env, bucket_log, tmp_path):
    """No credentials for the input: --anonymous reads the public bucket unsigned and converts, while
    the output (to the bucket) is written with the caller's credentials, the sequence's JSON strictly
    last; with no credentials and no --anonymous, one line names --anonymous."""
    import s3fs

    truth, _, local, _ = bucket_log
    env = no_credentials(s3_env, AWS_CONFIG_FILE=os.devnull, AWS_SHARED_CREDENTIALS_FILE=os.devnull)
    with LatencyProxy(s3_env["AWS_ENDPOINT_URL"]) as proxy:
        refused = convert_through(proxy, env, str(tmp_path / "refused"))
        assert "--anonymous" in one_line_error(refused) and "no credentials found" in refused.stderr
        proxy.reset()
        run = convert_through(proxy, s3_env, "s3://converted/anonymous", "--anonymous", "--no-validate")
        assert run.returncode == 0, run.stdout + run.stderr
        read = {path for _, path in proxy.order if path.startswith("/datasets")}
        written = {path for _, path in proxy.order if path.startswith("/converted")}
        assert read and not read & proxy.signed_paths, sorted(read & proxy.signed_paths)[:3]
        assert proxy.counts["PUT"] > 0 and written <= proxy.signed_paths, sorted(written - proxy.signed_paths)[:3]
        sequence = f"/converted/anonymous/{truth.log_id}/"
        puts = [path for kind, path in proxy.order if kind == "PUT" and path.startswith(sequence)]
        assert puts[-1] == f"{sequence}{truth.log_id}.json" and puts.count(puts[-1]) == 1, puts[-3:]
    s3fs.S3FileSystem(skip_instance_cache=True).get("converted/anonymous/", str(tmp_path / "got") + "/", recursive=True)
    assert hashes(tmp_path / "got") == local


@pytest.mark.parametrize(
    "code, anonymous, expected",
    [
        (
            "InvalidAccessKeyId",
            False,
            "the credentials were refused (InvalidAccessKeyId: invalid or expired); renew them",
        ),
        ("ExpiredToken", False, "the credentials were refused (ExpiredToken: invalid or expired); renew them"),
        ("AccessDenied", True, "access denied to an anonymous reader (not a public bucket); drop --anonymous"),
    ],
)
def test_each_credential_problem_is_one_line(s3_env, bucket_log, tmp_path, code, anonymous, expected):
    with LatencyProxy(s3_env["AWS_ENDPOINT_URL"], refuse=code) as proxy:
        run = convert_through(proxy, s3_env, str(tmp_path / "out"), *(["--anonymous"] if anonymous else []))
    assert one_line_error(run) == f"Error: --root-dir s3://datasets/av2: {expected}"


def test_a_silent_metadata_service_is_named(s3_env, bucket_log, tmp_path):
    """No credentials, and an instance metadata service that accepts connections but never answers."""
    with socket.socket() as silent:
        silent.bind(("127.0.0.1", 0))
        silent.listen(16)
        endpoint = f"http://127.0.0.1:{silent.getsockname()[1]}/"
        env = no_credentials(
            s3_env,
            AWS_EC2_METADATA_DISABLED="false",
            AWS_EC2_METADATA_SERVICE_ENDPOINT=endpoint,
            AWS_METADATA_SERVICE_TIMEOUT="1",
            AWS_METADATA_SERVICE_NUM_ATTEMPTS="1",
            AWS_CONFIG_FILE=os.devnull,
            AWS_SHARED_CREDENTIALS_FILE=os.devnull,
        )
        with LatencyProxy(s3_env["AWS_ENDPOINT_URL"]) as proxy:
            run = convert_through(proxy, env, str(tmp_path / "out"))
    line = one_line_error(run)
    assert f"the instance metadata service ({endpoint}) did not answer within 1 s" in line and "--anonymous" in line


def test_a_cooperative_scenario_from_the_bucket_converts_as_locally(s3_env, tmp_path):
    """OPV2V from the bucket: no HEAD, each object fetched whole once (validation's point counts
    read the PCDs' headers from the spooled copies), the source's bytes once, and the local output."""
    import s3fs

    synth = ["synth", "opv2v", "--out", str(tmp_path / "src"), "--frames", "3", "--cavs", "2"]
    made = subprocess.run([*av2_command("x", "y")[:1], *synth, "--lidar-columns", "64", "--render-step", "8"])
    assert made.returncode == 0
    fs = s3fs.S3FileSystem(skip_instance_cache=True)
    fs.mkdir("cooperative")
    fs.put(str(tmp_path / "src") + "/", "cooperative/opv2v/", recursive=True)
    files = [p.relative_to(tmp_path / "src").as_posix() for p in (tmp_path / "src").rglob("*") if p.is_file()]
    convert = ["--no-progress", "--workers", "2", "--output-dir"]
    local = subprocess.run(
        [*av2_command("x", "y")[:1], "--root-dir", str(tmp_path / "src"), *convert, str(tmp_path / "local")]
        + ["opv2v-v4", "--split", "test"],
        capture_output=True,
        text=True,
        env=s3_env,
    )
    assert local.returncode == 0, local.stdout + local.stderr
    with LatencyProxy(s3_env["AWS_ENDPOINT_URL"]) as proxy:
        run = subprocess.run(
            [*av2_command("x", "y")[:1], "--root-dir", "s3://cooperative/opv2v", *convert, str(tmp_path / "out")]
            + ["opv2v-v4", "--split", "test"],
            capture_output=True,
            text=True,
            env={**s3_env, "AWS_ENDPOINT_URL": proxy.url},
        )
        assert run.returncode == 0, run.stdout + run.stderr
        assert proxy.counts["HEAD"] == 0, sorted(p for k, p in proxy.keys if k == "HEAD")[:5]
        gets = {path: n for (kind, path), n in proxy.keys.items() if kind == "GET"}
        assert sorted(gets) == sorted(f"/cooperative/opv2v/{name}" for name in files)
        assert set(gets.values()) == {1}, sorted(p for p, n in gets.items() if n > 1)[:3]
        assert proxy.bytes_out == sum((tmp_path / "src" / name).stat().st_size for name in files)
    assert hashes(tmp_path / "out") == hashes(tmp_path / "local")


def test_the_reader_checks_each_object_against_its_listing_and_bounds_its_spool(s3_env, monkeypatch, tmp_path):
    """In this process: objects fetched ahead in order; one whose length differs from the listing's,
    or replaced since the listing (ETag), fails naming it; the spool keeps what fits in its bound,
    counts the rest, a second reader of the log (another job) takes the kept one from it without a
    request, and closing the reader that named the spool removes it."""
    import s3fs

    from ncore_convert.errors import SourceError
    from ncore_convert.sources import reader as reading
    from ncore_convert.sources.store import ObjectInfo, key

    fs = s3fs.S3FileSystem(skip_instance_cache=True)
    fs.mkdir("reader")
    for i in range(4):
        fs.pipe(f"reader/f/{i}.bin", bytes([i]) * 1000)
    folder = UPath("s3://reader/f", client_kwargs={"endpoint_url": s3_env["AWS_ENDPOINT_URL"]})  # not a cached client
    monkeypatch.setattr(reading, "SPOOL_BUDGET_BYTES", 2500)
    settings = reading.ReadSettings(spool_root=str(tmp_path))
    with reading.Reader(settings) as log_reader:
        listing = log_reader.list_folder(folder)
        paths = [folder / f"{i}.bin" for i in range(4)]
        assert [key(p) in listing for p in paths] == [True] * 4
        got = list(log_reader.read_ahead(paths, listing, keep=True))
        assert [data for _, data in got] == [bytes([i]) * 1000 for i in range(4)]
        counts = log_reader.counts
        assert (counts.lists, counts.gets, counts.bytes) == (1, 4, 4000)
        assert counts.spooled == 2 and counts.not_kept == 2
        assert "2 input file(s) not kept" in log_reader.not_kept_warning()
        with reading.Reader(log_reader.shared()) as job_reader:  # another job of the log
            assert job_reader.read(paths[0], listing) == bytes([0]) * 1000
            assert (job_reader.counts.gets, job_reader.counts.spool_hits) == (0, 1)
        assert log_reader.spool_dir.is_dir()  # a job's reader leaves the log's spool to its owner
        short = {key(paths[1]): ObjectInfo(999, None)}
        with pytest.raises(SourceError, match=r"1\.bin: object is 1000 bytes, its listing says 999"):
            log_reader.read(paths[1], short)
        fs.pipe("reader/f/2.bin", b"replaced" * 125)  # the same length, another ETag
        with pytest.raises(SourceError, match=r"2\.bin: object changed since its folder was listed"):
            log_reader.read(paths[2], listing)
    assert list(tmp_path.iterdir()) == []  # the log's reader closed: its spool is gone


def test_a_stop_aborts_the_multipart_uploads_of_the_sequence_being_published(s3_env, monkeypatch):
    """``stop.end`` aborts the unfinished multipart uploads under the folders this process is
    uploading to, and no other."""
    import s3fs

    from ncore_convert import storage

    fs = s3fs.S3FileSystem(skip_instance_cache=True)
    fs.mkdir("uploads")
    for key in ("out/log_a/log_a.ncore4.zarr.itar", "out/log_b/log_b.ncore4.zarr.itar"):
        upload = fs.call_s3("create_multipart_upload", Bucket="uploads", Key=key)
        fs.call_s3("upload_part", Bucket="uploads", Key=key, UploadId=upload["UploadId"], PartNumber=1, Body=b"x")
    endpoint = {"client_kwargs": {"endpoint_url": s3_env["AWS_ENDPOINT_URL"]}}  # not another module's server
    monkeypatch.setattr(storage, "_uploading", {UPath("s3://uploads/out/log_a", **endpoint)})
    storage.abort_uploads_in_flight()
    left = fs.call_s3("list_multipart_uploads", Bucket="uploads").get("Uploads", [])
    assert [u["Key"] for u in left] == ["out/log_b/log_b.ncore4.zarr.itar"]


def test_a_folder_of_more_than_a_thousand_objects_is_listed_whole(s3_env):
    """S3 lists 1,000 keys a page: the reader's one listing of a folder follows the pages (two LIST
    requests for 1,100 objects) and gives every object its size."""
    import s3fs

    from ncore_convert.sources.reader import Reader
    from ncore_convert.sources.store import key

    fs = s3fs.S3FileSystem(skip_instance_cache=True)
    fs.mkdir("paged")
    fs.pipe({f"paged/cam/{i:06d}.jpg": b"x" * (i % 7 + 1) for i in range(1100)})
    with LatencyProxy(s3_env["AWS_ENDPOINT_URL"]) as proxy:
        folder = UPath("s3://paged/cam", client_kwargs={"endpoint_url": proxy.url})
        with Reader() as reader:
            listing = reader.list_folder(folder)
        assert proxy.counts == {"LIST": 2}, proxy.counts
    assert len(listing) == 1100
    assert listing[key(folder / "000013.jpg")].size == 13 % 7 + 1


@pytest.fixture
def run_tmpdir():
    """An empty folder for a run's ``TMPDIR``, with a short path (the fork server's socket lives in it,
    and a Unix socket's path holds 107 bytes at most)."""
    folder = Path(tempfile.mkdtemp(prefix="nc-", dir="/tmp"))
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def test_two_logs_sharing_the_workers_count_their_own_requests(s3_env, tmp_path, run_tmpdir):
    """Two logs planned at once in one process (fewer logs than workers: their stores share the
    workers): the report's ``reads`` of each log are its own (every reader of the log added up: one
    GET per object of its folder, its bytes, its listings' bytes), no HEAD, and the finished run
    leaves nothing in its temporary folder."""
    import s3fs

    src = tmp_path / "src"
    logs = [
        write_log(UPath(src / "val"), SynthConfig(seconds=0.2, seed=s, camera_fps=5, camera_scale=4)) for s in (44, 45)
    ]
    fs = s3fs.S3FileSystem(skip_instance_cache=True)
    fs.mkdir("pair")
    fs.put(str(src / "val") + "/", "pair/av2/val/", recursive=True)
    sizes = {
        t.log_id: {
            p.relative_to(src).as_posix(): p.stat().st_size for p in (src / "val" / t.log_id).rglob("*") if p.is_file()
        }
        for t in logs
    }
    tmpdir = run_tmpdir
    with LatencyProxy(s3_env["AWS_ENDPOINT_URL"]) as proxy:
        env = {**s3_env, "AWS_ENDPOINT_URL": proxy.url, "TMPDIR": str(tmpdir)}
        command = av2_command("s3://pair/av2", str(tmp_path / "out"), "--workers", "3")
        run = subprocess.run(command, capture_output=True, text=True, timeout=600, env=env)
        assert run.returncode == 0, run.stdout + run.stderr
        assert proxy.counts["HEAD"] == 0
        gets = {path: n for (kind, path), n in proxy.keys.items() if kind == "GET"}
    report = json.loads((tmp_path / "out" / "conversion-report.json").read_text())["logs"]
    for log_id, files in sizes.items():
        fetched = {path: n for path, n in gets.items() if path.startswith(f"/pair/av2/val/{log_id}/")}
        assert sorted(fetched) == sorted(f"/pair/av2/{name}" for name in files) and set(fetched.values()) == {1}
        reads = report[log_id]["reads"]
        assert (reads["gets"], reads["bytes"]) == (len(files), sum(files.values())), (log_id, reads)
        assert reads["listed_bytes"] == report[log_id]["input_bytes"] == sum(files.values()), (log_id, reads)
        assert reads["spool_hits"] > 0 and reads["refetched"] == 0 == reads["not_kept"], (log_id, reads)
    assert list(tmpdir.iterdir()) == []


def test_validation_from_a_bucket_and_a_stopped_run_leave_no_temporary_folder(s3_env, bucket_log, tmp_path, run_tmpdir):
    """``validate --source s3://...`` keeps nothing on disk; a run from the bucket to the bucket,
    stopped while its spool holds fetched files, removes the spool, the log's staging folder and
    multiprocessing's folder on its way out."""
    _, _, _, tmp = bucket_log
    tmpdir = run_tmpdir
    env = {**s3_env, "TMPDIR": str(tmpdir)}
    command = av2_command("x", "y")[:1]
    validated = subprocess.run(
        [*command, "validate", "--source", "s3://datasets/av2", str(tmp / "local")],
        capture_output=True,
        text=True,
        env=env,
    )
    assert validated.returncode == 0, validated.stdout + validated.stderr
    assert list(tmpdir.iterdir()) == []
    run = subprocess.Popen(
        av2_command("s3://datasets/av2", "s3://converted/stopped", "--workers", "2"),  # staged under TMPDIR too
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    deadline = time.monotonic() + 120
    while not any(p.suffix != ".json" and ".feather." in p.name for p in tmpdir.rglob("*")):  # a spooled sweep
        assert run.poll() is None and time.monotonic() < deadline, "the run ended before it spooled a file"
        time.sleep(0.01)
    run.send_signal(signal.SIGTERM)
    stdout, stderr = run.communicate(timeout=60)
    assert run.returncode == 130, stdout + stderr
    assert list(tmpdir.iterdir()) == []
