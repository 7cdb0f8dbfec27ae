"""Converting from a bucket (issue 66): wall time, requests, bytes and peak RSS against one cloud
round trip per response, beside the same log on local disk.

A synthetic AV2 log (default: 4 s, seed 41: 857 files, 391 MB) is put in a moto S3 server behind
``tests/latency_proxy.py``, which holds each response's first byte D ms and counts HEAD, GET, LIST
and PUT requests and the bytes of GET bodies. The default command converts it (``--workers`` pinned,
input from the bucket; output local, or to the bucket with ``--output bucket``), at each D, and
from local disk; with ``--before REV`` the converter of that commit runs beside this tree's,
interleaved, on the same server. Each figure is the median of ``--repeats`` runs.

    python bench/bench_object_storage.py [--seconds 4] [--delays 0,20,50,100] [--output local|bucket]
        [--before REV] [--repeats 1] [--workers 2] [--faults]

Peak RSS is the largest of the run's processes (``ru_maxrss`` of the waited-for descendants).
The outputs' fingerprints (``bench/fingerprints.py``) are compared with the local conversion's.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "bench"))

from fingerprints import tree_hashes  # noqa: E402
from latency_proxy import LatencyProxy  # noqa: E402

BIN = Path(sys.executable).parent
CREDENTIALS = {"AWS_ACCESS_KEY_ID": "bench", "AWS_SECRET_ACCESS_KEY": "bench", "AWS_DEFAULT_REGION": "us-east-1"}
#: runs the command in a child and prints the largest RSS (KiB) among the run's processes
RUN = (
    "import resource, subprocess, sys, time; t = time.perf_counter();"
    " rc = subprocess.run(sys.argv[1:]).returncode;"
    " print(rc, time.perf_counter() - t, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, file=sys.stderr)"
)


def tree_fingerprint(root: Path) -> list[str]:
    """Every output file's SHA-256 (the run report aside: it holds wall-clock times)."""
    return tree_hashes(root, ("conversion-report.json",))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_moto() -> tuple[subprocess.Popen, str]:
    port = free_port()
    server = subprocess.Popen(
        [str(BIN / "moto_server"), "-H", "127.0.0.1", "-p", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 60
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return server, f"http://127.0.0.1:{port}"
        except OSError:
            if time.monotonic() > deadline:
                raise SystemExit("moto server did not start") from None
            time.sleep(0.2)


def command(root: str, out: str, workers: int) -> list[str]:
    """The default conversion command (the code on PYTHONPATH, else this tree's)."""
    code = "import sys; from ncore_convert.cli import main; sys.argv[0] = 'ncore-convert'; main()"
    args = ["--no-progress", "--root-dir", root, "--output-dir", out, "--workers", str(workers)]
    return [sys.executable, "-c", RUN, sys.executable, "-c", code, *args, "argoverse2-v4", "--split", "val"]


def timed(cmd: list[str], env: dict, src_path: str | None) -> tuple[float, int]:
    """(wall seconds, peak RSS in MiB of the largest process) of ``cmd`` with this tree's code, or
    ``src_path``'s (PYTHONPATH: the workers import it too); exits on a failed conversion."""
    env = {**env, "PYTHONPATH": src_path} if src_path else env
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    rc, wall, rss_kib = done.stderr.strip().splitlines()[-1].split()
    if int(rc) != 0:
        raise SystemExit(f"conversion failed:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    return float(wall), int(rss_kib) // 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--seed", type=int, default=41)
    parser.add_argument("--delays", default="0,20,50,100")
    parser.add_argument("--output", choices=["local", "bucket"], default="local")
    parser.add_argument("--before", default=None, help="a commit whose converter runs beside this tree's")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--faults", action="store_true", help="also 2 %% 503 SlowDown and 1 %% dropped connections")
    parser.add_argument("--work", default=None)
    args = parser.parse_args()
    work = Path(args.work or tempfile.mkdtemp(prefix="bench-object-storage-"))
    src = work / "src"
    if not (src / "val").is_dir():
        synth = ["synth", "argoverse2", "--out", str(src), "--seconds", str(args.seconds), "--pictures", "16"]
        subprocess.run([str(BIN / "ncore-convert"), *synth, "--seed", str(args.seed)], check=True, capture_output=True)
    files = [p for p in src.rglob("*") if p.is_file()]
    source_bytes = sum(p.stat().st_size for p in files)
    mb = source_bytes / 1e6
    print(f"log: {args.seconds:g} s, seed {args.seed}: {len(files)} files, {mb:.0f} MB; workers {args.workers}")

    versions = {"after": None}
    if args.before:
        tree = work / f"before-{args.before}"
        if not tree.exists():
            subprocess.run(["git", "-C", str(REPO), "worktree", "add", "-f", str(tree), args.before], check=True)
        versions = {"before": str(tree / "src"), "after": None}

    server, moto_url = start_moto()
    env = {**os.environ, **CREDENTIALS}
    try:
        import s3fs

        os.environ.update(CREDENTIALS)
        fs = s3fs.S3FileSystem(client_kwargs={"endpoint_url": moto_url})
        fs.mkdir("datasets")
        fs.mkdir("converted")
        fs.put(str(src) + "/", "datasets/av2/", recursive=True)

        local_fp = None
        rows = []
        for name, code in versions.items():
            walls, rss = [], []
            for r in range(args.repeats):
                out = work / f"local-{name}-{r}"
                shutil.rmtree(out, ignore_errors=True)  # a fresh output: nothing resumed
                wall, peak = timed(command(str(src), str(out), args.workers), env, code)
                walls.append(wall)
                rss.append(peak)
                local_fp = local_fp or tree_fingerprint(out)
            rows.append((name, "local disk", statistics.median(walls), None, None, statistics.median(rss), True))
        for delay in [float(d) for d in args.delays.split(",")]:
            faults = {"slow_down": 0.02, "drop": 0.01, "seed": 66} if args.faults else {}
            with LatencyProxy(moto_url, delay, **faults) as proxy:
                for name, code in versions.items():
                    walls, rss, counts = [], [], None
                    for r in range(args.repeats):
                        proxy.reset()
                        tag = f"{name}-{int(delay)}-{r}"
                        out = f"s3://converted/{tag}" if args.output == "bucket" else str(work / f"out-{tag}")
                        shutil.rmtree(work / f"out-{tag}", ignore_errors=True)
                        shutil.rmtree(work / f"got-{tag}", ignore_errors=True)
                        if fs.exists(f"converted/{tag}"):
                            fs.rm(f"converted/{tag}", recursive=True)
                        run_env = {**env, "AWS_ENDPOINT_URL": proxy.url}
                        wall, peak = timed(command("s3://datasets/av2", out, args.workers), run_env, code)
                        walls.append(wall)
                        rss.append(peak)
                        counts = (dict(proxy.counts), proxy.bytes_out, proxy.busy_s / wall, dict(proxy.faults))
                        again = sorted(k for k, n in proxy.keys.items() if n > 1 and k[0] == "GET")
                        heads = sorted(k[1] for k in proxy.keys if k[0] == "HEAD")
                        print(f"{name}, D = {delay:g} ms: fetched again {again[:3]} ({len(again)}); HEAD {heads[:3]}")
                        if args.output == "local":
                            same = tree_fingerprint(Path(out)) == local_fp
                        else:
                            fs.get(out.removeprefix("s3://") + "/", str(work / f"got-{tag}") + "/", recursive=True)
                            same = tree_fingerprint(work / f"got-{tag}") == local_fp
                    where = f"bucket, D = {delay:g} ms"
                    rows.append((name, where, statistics.median(walls), counts, delay, statistics.median(rss), same))
    finally:
        server.terminate()
        server.wait(timeout=30)

    print(f"\noutput {args.output}; {len(files)} objects, {source_bytes / 1e6:.0f} MB in the source\n")
    print(
        "| version | source | wall | ÷ D = 0 | requests (HEAD/GET/LIST/PUT) | per object | bytes fetched ÷ source"
        " | in flight | peak RSS | identical |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    base = {name: wall for name, where, wall, _, delay, _, _ in rows if delay == 0}
    for name, where, wall, counts, _, rss, same in rows:
        if counts is None:
            print(f"| {name} | {where} | {wall:.1f} s | | | | | | {rss} MB | {same} |")
            continue
        kinds, fetched, in_flight, faults = counts
        total = sum(kinds.values())
        split = "/".join(str(kinds.get(k, 0)) for k in ("HEAD", "GET", "LIST", "PUT"))
        ratio = wall / base[name] if name in base else float("nan")
        fault_note = f" (faults {faults})" if faults else ""
        print(
            f"| {name} | {where} | {wall:.1f} s | {ratio:.2f} | {total} ({split}){fault_note}"
            f" | {total / len(files):.2f} | {fetched / source_bytes:.2f} | {in_flight:.1f} | {rss} MB | {same} |"
        )
    print(json.dumps({"work": str(work)}))


if __name__ == "__main__":
    main()
