"""The ego-mask seed sweep: how often the estimator writes a right mask, a confidently wrong one,
or declines, over many synthetic logs (issue 39).

Not a test: it measures no time, only outcomes, over more logs than a test suite can afford. Each
log is a 1.5 s synthetic AV2 or TbV log (3 s when half parked) with 20 fps cameras cycling 32
distinct pictures (as many as the estimator samples), no lidar, and images only for the cameras
with a body (the calibration rules the others out before any image is read), so a log here is
not the one ``synth`` writes for the same seed. ``synth`` makes it with the given body and light;
its masks are planned exactly as ``argoverse2-v4`` / ``tbv-v4`` plan them (``plan_ego_masks``: the
same sampling, decoding and decision) and compared at full resolution with the generator's true
body. Per group of logs, over the cameras that see the body:

- **right**: a mask written with IoU >= 0.95;
- **close**: a mask written with 0.9 <= IoU < 0.95;
- **confident wrong**: a mask written with IoU < 0.9;
- **declined**: no mask (with a warning, and the reason in the camera's metadata);

and over the cameras that do not see the body, how many got a mask (0 is right). For the cameras
declined because the log's halves disagree, it also estimates the mask with that test switched
off and scores it: what the test prevented.

Groups: the main sweep, ``--seeds`` seeds x {AV2, TbV} x {realistic, easy} bodies by day; and
the generator's hard cases, ``--hard-seeds`` seeds x {AV2, TbV} each: a parked ego (the world
still for the whole log), half parked (still for the first 1.5 s of 3), night-like exposure (a
dark world lit by moving lamps), strong reflections of the moving world in the paint (the
``glossy`` body), and moving shadows across the body and the world.

    python bench/bench_ego_sweep.py [--seeds 100] [--hard-seeds 25] [--first-seed 1000] [--jobs 2]
                                    [--out sweep.jsonl] [--keep DIR]

With ``--keep``, the logs are written once and a later run only plans and scores them (the whole
sweep then takes minutes, not the better part of two hours).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from functools import partial

import numpy as np

#: (group name, SynthConfig fields) of the hard cases, realistic body unless said.
HARD_CASES = {
    "parked": {"parked_fraction": 1.0},
    "half parked": {"parked_fraction": 0.5, "seconds": 3.0},  # 3 s: 30 moving images, enough for two halves
    "night": {"light": "night"},
    "strong reflections": {"ego_body": "glossy"},
    "moving shadows": {"shadows": True},
}


@dataclass(frozen=True)
class Case:
    group: str
    tbv: bool
    seed: int
    config: dict


def config(case: Case):
    """The case's ``SynthConfig``."""
    from ncore_convert.synth.argoverse2 import SynthConfig
    from ncore_convert.synth.ego import EGO_CAMERAS

    return SynthConfig(
        **{
            "seconds": 1.5,
            "seed": case.seed,
            "camera_fps": 20,
            "pictures": 32,
            "tbv": case.tbv,
            "sweeps": False,
            "image_cameras": EGO_CAMERAS,
            **case.config,
        }
    )


def log_folder(case: Case, synth_config) -> str:
    """The folder name of the case's log (``synth_config``: its ``config``) under ``--keep``:
    another config is another log."""
    digest = hashlib.sha1(repr(synth_config).encode()).hexdigest()[:10]
    return f"{case.group.replace(' ', '_')}_{'TbV' if case.tbv else 'AV2'}_{case.seed}_{digest}"


def _log(case: Case, folder: str):
    """Synthesise the case's log into ``folder`` (or find it there from an earlier run, as the
    generator is deterministic per seed and config): its directory, config and true ego pixels."""
    from upath import UPath

    from ncore_convert.synth.argoverse2 import write_log

    synth_config = config(case)
    home = UPath(folder) / log_folder(case, synth_config)
    done = home / "truth.npz"
    if not done.exists():  # written last: a log without it is incomplete and made again
        shutil.rmtree(home, ignore_errors=True)
        truth = write_log(home, synth_config)
        np.savez_compressed(done, log_id=truth.log_id, **{f"mask_{cam}": m for cam, m in truth.ego_masks.items()})
    with np.load(done) as stored:
        masks = {key.removeprefix("mask_"): stored[key] for key in stored.files if key.startswith("mask_")}
        return home / str(stored["log_id"]), synth_config, masks


def _run(case: Case, keep: str | None = None) -> list[dict]:
    """Synthesise one log (or reuse it from ``keep``), plan its masks as the converter does, and
    score every camera."""
    from ncore_convert.converters.argoverse2 import masks as planning
    from ncore_convert.converters.argoverse2.plan import camera_pinhole
    from ncore_convert.sources import argoverse2 as av2
    from ncore_convert.transforms.camera.ego_mask import EgoBox

    with tempfile.TemporaryDirectory() as tmp:
        log_dir, synth_config, true_masks = _log(case, keep or tmp)
        intrinsics, extrinsics = av2.read_intrinsics(log_dir), av2.read_sensor_extrinsics(log_dir)
        cameras = {
            cam: (av2.list_image_timestamps_ns(log_dir, cam), camera_pinhole(intrinsics[cam]), extrinsics[cam])
            for cam in synth_config.cameras
        }
        started = time.perf_counter()
        masks = planning.plan_ego_masks(log_dir, "estimate", cameras, [], EgoBox())
        seconds = time.perf_counter() - started
        # What the agreement test prevented: the mask from all the images, had it not been asked.
        unchecked = {
            cam: _without_agreement(planning, log_dir, cam, *cameras[cam])
            for cam, planned in masks.items()
            if planned.meta["decision"] == "halves disagree"
        }
    rows = []
    for cam, planned in masks.items():
        intr = intrinsics[cam]
        true = true_masks.get(cam)
        row = {
            "group": case.group,
            "dataset": "TbV" if case.tbv else "AV2",
            "seed": case.seed,
            "camera": cam,
            "body": true is not None,
            "decision": planned.meta["decision"],
            "iou": None,
            "unchecked_iou": None,
            "split_iou": planned.meta.get("split_iou"),
            "split_columns": planned.meta.get("split_columns"),
            "estimate_s": seconds,
        }
        for key, mask in (("iou", planned), ("unchecked_iou", unchecked.get(cam))):
            image = mask.image(intr.width_px, intr.height_px) if mask is not None else None
            if image is not None:
                written = np.asarray(image) > 0
                row[key] = float((written & true).sum() / (written | true).sum()) if true is not None else 0.0
        rows.append(row)
    return rows


def _without_agreement(planning, log_dir, camera: str, *inputs):
    """The camera's estimate with the split-log agreement not asked."""
    from ncore_convert.transforms.camera.ego_mask import EgoBox

    return planning._estimate(log_dir, camera, *inputs, EgoBox(), require_agreement=False)


def cases(seeds: int, hard_seeds: int, first_seed: int) -> list[Case]:
    out = []
    for seed in range(first_seed, first_seed + seeds):
        for tbv in (False, True):
            for body in ("realistic", "easy"):
                out.append(Case(f"main {body}", tbv, seed, {"ego_body": body}))
    for name, fields in HARD_CASES.items():
        for seed in range(first_seed, first_seed + hard_seeds):
            for tbv in (False, True):
                out.append(Case(name, tbv, seed, fields))
    return out


def summarise(rows: list[dict]) -> None:
    groups: dict[tuple[str, str], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["group"], row["dataset"]), []).append(row)
    print(
        f"{'group':<20} {'set':<4} {'logs':>5} {'body cams':>9} {'right':>7} {'close':>6} {'WRONG':>6}"
        f" {'declined':>9} {'right %':>8} {'no-body cams':>12} {'masks there':>11}"
    )
    total = Counter()
    for (group, dataset), members in sorted(groups.items()):
        body = [r for r in members if r["body"]]
        other = [r for r in members if not r["body"]]
        written = [r for r in body if r["iou"] is not None]
        right = sum(r["iou"] >= 0.95 for r in written)
        close = sum(0.9 <= r["iou"] < 0.95 for r in written)
        wrong = sum(r["iou"] < 0.9 for r in written)
        false_masks = sum(r["iou"] is not None for r in other)
        logs = len({r["seed"] for r in members})
        print(
            f"{group:<20} {dataset:<4} {logs:>5} {len(body):>9} {right:>7} {close:>6} {wrong:>6}"
            f" {len(body) - len(written):>9} {100 * right / max(len(body), 1):>7.1f}% {len(other):>12}"
            f" {false_masks:>11}"
        )
        key = "main" if group.startswith("main") else "hard"
        total.update(
            {
                f"{key} body": len(body),
                f"{key} right": right,
                f"{key} close": close,
                f"{key} wrong": wrong,
                f"{key} false": false_masks,
            }
        )
    for key in ("main", "hard"):
        if total[f"{key} body"]:
            print(
                f"{key} cases: {total[f'{key} body']} body cameras, {total[f'{key} right']} right"
                f" ({100 * total[f'{key} right'] / total[f'{key} body']:.1f} %), {total[f'{key} close']} close,"
                f" {total[f'{key} wrong']} confident wrong; {total[f'{key} false']} masks on cameras"
                " without the body"
            )
    declined = Counter(r["decision"] for r in rows if r["body"] and r["iou"] is None)
    print("declined body cameras by reason:", dict(declined.most_common()))
    caught = [r["unchecked_iou"] for r in rows if r["decision"] == "halves disagree" and r["body"]]
    print(
        f"the split-log agreement declined {len(caught)} body cameras; without it their masks would have had"
        f" IoU >= 0.95: {sum(i is not None and i >= 0.95 for i in caught)}, 0.9-0.95:"
        f" {sum(i is not None and 0.9 <= i < 0.95 for i in caught)}, < 0.9 (confident wrong):"
        f" {sum(i is not None and i < 0.9 for i in caught)}"
    )
    written = [r for r in rows if r["iou"] is not None and r["body"]]
    if written:
        print(
            f"written masks: IoU with the truth >= {min(r['iou'] for r in written):.3f}; split IoU >="
            f" {min(r['split_iou'] for r in written):.3f}, columns >= {min(r['split_columns'] for r in written):.3f}"
        )
    wrong = [r for r in rows if r["iou"] is not None and (not r["body"] or r["iou"] < 0.9)]
    for r in wrong:
        print(
            f"  confident wrong: {r['group']} {r['dataset']} seed {r['seed']} {r['camera']} IoU {r['iou']:.3f}"
            f" (split IoU {r['split_iou']}, columns {r['split_columns']})"
        )
    times = sorted({(r["group"], r["dataset"], r["seed"]): r["estimate_s"] for r in rows}.values())
    print(f"estimation per log (all cameras, threads): median {np.median(times):.2f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=100)
    parser.add_argument("--hard-seeds", type=int, default=25)
    parser.add_argument("--first-seed", type=int, default=1000, help="the tests use seeds 31-48: stay clear")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--out", help="write every camera's row here (JSON lines)")
    parser.add_argument(
        "--keep",
        help="keep the synthesised logs in this folder and reuse them on later runs (about"
        " 25 MB a log, named by its config; delete it when the generator changes)",
    )
    args = parser.parse_args()
    todo = cases(args.seeds, args.hard_seeds, args.first_seed)
    print(f"{len(todo)} logs on {args.jobs} processes", flush=True)
    rows: list[dict] = []
    started = time.perf_counter()
    out = open(args.out, "w") if args.out else None  # noqa: SIM115 (written row by row, as logs finish)
    with ProcessPoolExecutor(args.jobs) as pool:
        for i, result in enumerate(pool.map(partial(_run, keep=args.keep), todo, chunksize=1), 1):
            rows.extend(result)
            if out:
                out.writelines(json.dumps(row) + "\n" for row in result)
                out.flush()
            if i % 20 == 0 or i == len(todo):
                print(f"  {i}/{len(todo)} logs, {time.perf_counter() - started:.0f} s", flush=True)
    if out:
        out.close()
    summarise(rows)


if __name__ == "__main__":
    main()
