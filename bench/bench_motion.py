"""Movers from the lidar alone (issue 53, ``transforms.lidar.free_space``) on synthetic TbV logs,
against the generator's truth: which scene object each return hit, and whether it moved faster than
0.2 m/s at the return's own time.

The generator's returns go in as the lidar measured them (each unit's points in the city frame, where
the unit was as it fired, its beam); the sweeps stream through ``motion_window.MotionWindow``. Per seed: SA (static
returns not flagged / static returns), DA (moving returns flagged / moving returns), HA (their
harmonic mean), DA on the first and the last sweep, the milliseconds a sweep (building the sweeps'
images; flagging) and the most memory the stream held (numpy's arrays, tracemalloc; a run of its
own). Seeds 201-202 were looked at while the method was made; the default seeds were not.

``--dufomap`` runs DUFOMap (``pip install dufomap``: Duberg, Zhang et al., RA-L 2024) with its
paper's defaults (0.1 m voxels, d_s 0.2, d_p 1; 2 threads) on the same sweeps, side by side: each
unit's returns of a sweep integrated from where that unit was in the middle of the sweep, in time
order, then propagated once and every sweep segmented; its milliseconds a sweep and the resident
memory it added.

``--conversion`` measures what the flags cost a whole TbV conversion: a synthetic TbV log (seed 17,
seven ring cameras at 20 fps, ``--conversion-seconds``) converted in one process (the dataset-run
mode's one worker per log), alternately with ``--dynamic-source lidar`` (TbV's default) and
``annotations`` (no flags), ``--repeat`` rounds: the wall times, the seconds the flags took
(``dynamic_flag_seconds``: building the sweeps' images, flagging, and the flags on the points), and
their share of the conversion; medians.

``--both`` measures what ``--dynamic-source both`` adds to the annotations on AV2: a synthetic AV2
log per seed whose annotators missed every other moving track (their rows taken out of
``annotations.feather``, as for a class outside the taxonomy), converted with ``annotations`` and
with ``both``; per point against the truth: SA, DA over every mover, DA over the unannotated movers,
and the standing tracks' points flagged.

    python bench/bench_motion.py [--seeds 203,204,205] [--seconds 4] [--dufomap]
    python bench/bench_motion.py --conversion [--conversion-seconds 5] [--repeat 3]
    python bench/bench_motion.py --both [--seeds 203,204,205] [--seconds 4]
"""

from __future__ import annotations

import shutil
import statistics
import time
import tracemalloc
from pathlib import Path

import numpy as np
from bench_argoverse2 import bench_parser, work_dir
from upath import UPath

from ncore_convert.synth.argoverse2 import SynthConfig, write_log
from ncore_convert.transforms.lidar import free_space, motion_window

MOVING_MPS = 0.2  #: issue 53: a return is on a mover when its object moves faster than this at its time


def _rss_mb() -> float:
    """This process's resident memory, MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def dufomap_flags(sweeps: list[dict[str, np.ndarray]]) -> tuple[list[np.ndarray], float, float]:
    """DUFOMap's labels of every return (bool [N] per sweep), its seconds a sweep and the MB it added."""
    from dufomap import dufomap

    before = _rss_mb()
    started = time.perf_counter()
    mapper = dufomap(0.1, 0.2, 1, num_threads=2)
    parts = []
    for s in sweeps:
        for u in (0, 1):
            mine = s["unit"] == u
            pose = np.eye(4)
            pose[:3, 3] = s["origin_m"][mine].mean(axis=0)
            parts.append((mine, pose))
            mapper.run(s["xyz_m"][mine], pose, cloud_transform=False)
    mapper.oncePropagateCluster(if_propagate=True, if_cluster=False)
    flags = []
    for k, s in enumerate(sweeps):
        flag = np.zeros(len(s["unit"]), bool)
        for u in (0, 1):
            mine, pose = parts[2 * k + u]
            flag[mine] = mapper.segment(s["xyz_m"][mine], pose, cloud_transform=False) == 1
        flags.append(flag)
    seconds = (time.perf_counter() - started) / len(sweeps)
    return flags, seconds, _rss_mb() - before


def _figures(sweeps: list[dict[str, np.ndarray]], flagged: list[np.ndarray]) -> dict:
    """SA, DA, HA and DA on the first and last sweep of ``flagged`` (bool [N] per sweep)."""
    static_ok = static = moving_ok = moving = 0
    for s, dynamic in zip(sweeps, flagged, strict=True):
        truth = s["moving"]
        static_ok += int((~dynamic & ~truth).sum())
        static += int((~truth).sum())
        moving_ok += int((dynamic & truth).sum())
        moving += int(truth.sum())
    sa, da = static_ok / static, moving_ok / max(moving, 1)
    ends = [
        (d & s["moving"]).sum() / max(s["moving"].sum(), 1)
        for s, d in ((sweeps[0], flagged[0]), (sweeps[-1], flagged[-1]))
    ]
    return {"SA": sa, "DA": da, "HA": 2 * sa * da / (sa + da), "DA first": ends[0], "DA last": ends[1]}


def _stream(sweeps: list[dict[str, np.ndarray]], keep: bool = True) -> tuple[list, float, float]:
    """Stream ``sweeps`` through ``motion_window.MotionWindow``, each sweep's images built as it arrives: the flags
    (index, ``SweepFlags``; none unless ``keep``: a converter hands each on), the seconds building and
    flagging."""
    built = spent = 0.0
    window, flagged = motion_window.MotionWindow(), []
    for s in sweeps:
        started = time.perf_counter()
        units = [
            free_space.SweepSight(s["xyz_m"][s["unit"] == u], s["origin_m"][s["unit"] == u], s["beam"][s["unit"] == u])
            for u in (0, 1)
        ]
        built += time.perf_counter() - started
        started = time.perf_counter()
        ready = window.push(units)
        spent += time.perf_counter() - started
        flagged += ready if keep else []
    started = time.perf_counter()
    flagged += window.finish() if keep else []
    return flagged, built, spent + time.perf_counter() - started


def peak_mb(sweeps: list[dict[str, np.ndarray]]) -> float:
    """The most memory (MB, numpy's arrays through tracemalloc) streaming ``sweeps`` holds at once."""
    tracemalloc.start()
    base = tracemalloc.get_traced_memory()[0]
    _stream(sweeps, keep=False)
    peak = tracemalloc.get_traced_memory()[1] - base
    tracemalloc.stop()
    return peak / 1e6


def score(sweeps: list[dict[str, np.ndarray]]) -> dict:
    """Stream ``sweeps`` through ``motion_window.MotionWindow`` and score it."""
    flagged, built, spent = _stream(sweeps)
    by_sweep, unknown = [None] * len(sweeps), [None] * len(sweeps)
    for k, flags in flagged:
        s = sweeps[k]
        order = np.concatenate([np.flatnonzero(s["unit"] == u) for u in (0, 1)])
        by_sweep[k], unknown[k] = np.zeros(len(order), bool), np.zeros(len(order), bool)
        by_sweep[k][order] = flags.dynamic
        unknown[k][order] = flags.not_judged
    moving = sum(int(s["moving"].sum()) for s in sweeps)
    static = sum(int((~s["moving"]).sum()) for s in sweeps)
    missed = sum(int((s["moving"] & ~d).sum()) for s, d in zip(sweeps, by_sweep, strict=True))
    return {
        **_figures(sweeps, by_sweep),
        "unknown": sum(int(u.sum()) for u in unknown) / (moving + static),
        "static unknown": sum(int((u & ~s["moving"]).sum()) for s, u in zip(sweeps, unknown, strict=True)) / static,
        "missed unknown": sum(int((u & s["moving"]).sum()) for s, u in zip(sweeps, unknown, strict=True))
        / max(missed, 1),
        "build ms": 1e3 * built / len(sweeps),
        "flag ms": 1e3 * spent / len(sweeps),
        "moving share": moving / (moving + static),
    }


def conversion_share(work: Path, seconds: float, repeat: int) -> None:
    """What the lidar's flags cost a whole TbV conversion (see the module docstring)."""
    from bench_argoverse2 import cached

    from ncore_convert.converters.argoverse2 import Argoverse2Options, convert_log

    root = work / f"tbv-cost-{seconds:g}s"
    log_id = cached(
        root,
        f"{seconds:g} s TbV log",
        lambda r: write_log(UPath(r), SynthConfig(seconds=seconds, seed=17, tbv=True)).log_id,
    )
    runs = []
    for _ in range(repeat):
        run = {}
        for source in ("lidar", "annotations"):
            out = work / "tbv-cost-out" / source
            shutil.rmtree(out, ignore_errors=True)
            started = time.perf_counter()
            summary = convert_log(UPath(root), UPath(out), log_id, Argoverse2Options(split=None, dynamic_source=source))
            run[f"{source} s"] = time.perf_counter() - started
            if source == "lidar":
                run["flags s"] = summary.dynamic_flag_seconds
        run["flags share"] = run["flags s"] / run["lidar s"]
        run["wall share"] = (run["lidar s"] - run["annotations s"]) / run["lidar s"]
        runs.append(run)
        print("  " + ", ".join(f"{k} {v:.3f}" for k, v in run.items()), flush=True)
    print(f"{seconds:g} s TbV log with its cameras, one process, medians of {repeat}:")
    for key in runs[0]:
        print(f"  {key:<16} {statistics.median(r[key] for r in runs):.3f}")
    shutil.rmtree(work / "tbv-cost-out", ignore_errors=True)


def both_gain(work: Path, seeds: list[int], seconds: float) -> None:
    """What ``--dynamic-source both`` adds to annotations that miss movers (see the module docstring)."""
    import pyarrow.compute
    import pyarrow.feather
    from ncore.data.v4 import SequenceComponentGroupsReader, SequenceLoaderV4

    from ncore_convert.converters.argoverse2 import Argoverse2Options, convert_log
    from ncore_convert.sources import argoverse2 as av2
    from ncore_convert.synth.feather import write_feather_table

    rows = {}
    for seed in seeds:
        root = work / f"both-{seed}"
        shutil.rmtree(root, ignore_errors=True)
        config = SynthConfig(seconds=seconds, seed=seed, keep_truth=True, camera_fps=0, clear_paths=True)
        truth = write_log(UPath(root / "src" / "val"), config)
        movers = [b for b in truth.scene.boxes if b.annotated and b.moved_m(0.0, seconds) > 1.0]
        missed = {b.track_uuid for b in movers[::2]}
        path = truth.log_dir / "annotations.feather"
        table = pyarrow.feather.read_table(str(path))
        kept = table.filter(
            pyarrow.compute.invert(pyarrow.compute.is_in(table["track_uuid"], pyarrow.array(list(missed))))
        )
        write_feather_table(UPath(path), av2.ANNOTATIONS_SCHEMA, kept.to_pydict())
        index_missed = np.array([b.track_uuid in missed for b in truth.scene.boxes] + [False])
        standing = np.array([b.annotated and b.moved_m(0.0, seconds) == 0.0 for b in truth.scene.boxes] + [False])
        row = {}
        for source in ("annotations", "both"):
            out = root / source
            options = Argoverse2Options(split="val", dynamic_source=source, camera_ids=())
            convert_log(UPath(root / "src"), UPath(out), truth.log_id, options)
            loader = SequenceLoaderV4(SequenceComponentGroupsReader([UPath(out / f"{truth.log_id}.json")]))
            sources = [loader.get_point_clouds_source(unit) for unit in av2.LIDARS]
            counts = np.zeros(7)
            for k, sweep in enumerate(truth.sweeps):
                moving = truth.sweep_returns(k, MOVING_MPS)["moving"]
                for u, points in enumerate(sources):
                    flag = points.get_pc_generic_data(k, "dynamic_flag") == 1
                    mine = sweep.unit == u
                    truly, box = moving[mine], sweep.box_index[mine]
                    unannotated = truly & index_missed[box]
                    counts += [
                        (~flag & ~truly).sum(),
                        (~truly).sum(),
                        (flag & truly).sum(),
                        truly.sum(),
                        (flag & unannotated).sum(),
                        unannotated.sum(),
                        (flag & standing[box]).sum(),
                    ]
            row[f"{source} SA"], row[f"{source} DA"] = counts[0] / counts[1], counts[2] / counts[3]
            row[f"{source} DA unannotated"] = counts[4] / max(counts[5], 1)
            row[f"{source} standing flagged"] = counts[6]
        rows[seed] = row
        print(
            f"  seed {seed} ({len(missed)} of {len(movers)} moving tracks unannotated): "
            + ", ".join(f"{k} {v:.4f}" for k, v in row.items()),
            flush=True,
        )
    print(f"{seconds:g} s synthetic AV2 logs, seeds {seeds}: medians")
    for key in next(iter(rows.values())):
        print(f"  {key:<34} {statistics.median(r[key] for r in rows.values()):.4f}")


def main() -> None:
    parser = bench_parser(__doc__, repeat=1)
    parser.add_argument("--seeds", default="203,204,205")
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--dufomap", action="store_true", help="run DUFOMap side by side (pip install dufomap)")
    parser.add_argument("--conversion", action="store_true", help="the flags' share of a whole TbV conversion")
    parser.add_argument("--conversion-seconds", type=float, default=5.0)
    parser.add_argument("--both", action="store_true", help="what --dynamic-source both adds to annotations")
    parser.add_argument(
        "--overlapping-traffic", action="store_true", help="the generator's old worlds (movers through parked cars)"
    )
    args = parser.parse_args()
    work = work_dir(args) / "motion"
    if args.both:
        both_gain(work, [int(s) for s in args.seeds.split(",")], args.seconds)
        return
    if args.conversion:
        conversion_share(work, args.conversion_seconds, args.repeat)
        return
    rows = {}
    for seed in (int(s) for s in args.seeds.split(",")):
        config = SynthConfig(
            seconds=args.seconds,
            seed=seed,
            tbv=True,
            keep_truth=True,
            camera_fps=0,
            clear_paths=not args.overlapping_traffic,
        )
        truth = write_log(UPath(work / str(seed)), config)
        sweeps = [truth.sweep_returns(k, MOVING_MPS) for k in range(len(truth.sweeps))]
        rows[seed] = score(sweeps)
        rows[seed]["MB"] = peak_mb(sweeps)
        if args.dufomap:
            flags, seconds, added_mb = dufomap_flags(sweeps)
            figures = _figures(sweeps, flags)
            rows[seed].update({f"DUFOMap {k}": v for k, v in figures.items()})
            rows[seed].update({"DUFOMap ms": 1e3 * seconds, "DUFOMap MB": added_mb})
            ours_ms = rows[seed]["build ms"] + rows[seed]["flag ms"]
            rows[seed]["speed-up"] = rows[seed]["DUFOMap ms"] / ours_ms
        print(
            f"  seed {seed}: " + ", ".join(f"{k} {v:.4f}" if v < 10 else f"{k} {v:.0f}" for k, v in rows[seed].items()),
            flush=True,
        )
    print(f"{args.seconds:g} s synthetic TbV logs, seeds {args.seeds}: medians")
    for key in next(iter(rows.values())):
        print(f"  {key:<14} {statistics.median(r[key] for r in rows.values()):.4f}")


if __name__ == "__main__":
    main()
