"""False alarms of the validator on correct generated logs (issue 65): how many logs a validation
refuses, and by which check, before (the validator of ``--before``, default bef5368) and after (this
tree), on the same conversions.

At least 100 logs: AV2 (1 s and 4 s), TbV, OPV2V and V2XSet, generated with and without ``--shapes``
and ``--close-range``, converted with the converter's default options (cameras off in the generator:
the checks that refused logs are the lidar's) without and with a clip window, on seeds that no test
uses (7001...). Each log is converted once with ``--no-validate``; both validators then read the same
output (``ncore-convert validate --source``, the checks a conversion runs before it publishes).

    python bench/bench_false_alarms.py [--before REV] [--seeds-per-combo N] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-c", "import sys; from ncore_convert.cli import main; sys.argv[0] = 'ncore-convert'; main()"]
CLIP = ["--seek-sec", "0.2", "--duration-sec", "0.6"]
COMBOS = [[], ["--shapes"], ["--close-range"], ["--shapes", "--close-range"]]


def run(args: list[str], env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(CLI + args, capture_output=True, text=True, env=env)


def groups(per_combo: int) -> list[dict]:
    """The generated datasets: name, synth command, converter command, the logs' seeds."""
    seed = iter(range(7001, 9000))
    out = []
    for combo in COMBOS:
        out.append(
            dict(
                name="av2-1s",
                kind="argoverse2",
                seconds=1.0,
                combo=combo,
                seeds=[next(seed) for _ in range(2 * per_combo)],
            )
        )
    for combo in (COMBOS[0], COMBOS[3]):
        out.append(
            dict(
                name="av2-4s",
                kind="argoverse2",
                seconds=4.0,
                combo=combo,
                seeds=[next(seed) for _ in range(max(1, per_combo // 3))],
            )
        )
        out.append(
            dict(
                name="tbv-1s",
                kind="tbv",
                seconds=1.0,
                combo=combo,
                seeds=[next(seed) for _ in range(max(1, per_combo // 2))],
            )
        )
    for combo in COMBOS:
        out.append(dict(name="opv2v", kind="opv2v", combo=combo, seeds=[next(seed)], scenarios=max(1, per_combo // 4)))
    for combo in (COMBOS[0], COMBOS[3]):
        out.append(
            dict(name="v2xset", kind="v2xset", combo=combo, seeds=[next(seed)], scenarios=max(1, per_combo // 4))
        )
    return out


def generate(group: dict, root: Path) -> tuple[list[str], list[str]]:
    """Write a group's logs under ``root``; return the converter's command (after the group options)
    and its dataset arguments."""
    kind, combo = group["kind"], group["combo"]
    if kind in ("argoverse2", "tbv"):
        for seed in group["seeds"]:
            args = ["synth", kind, "--out", str(root), "--seconds", str(group["seconds"]), "--seed", str(seed)]
            check(run(args + ["--camera-fps", "0", *combo]))
        return (["argoverse2-v4", "--split", "val"] if kind == "argoverse2" else ["tbv-v4"]), []
    args = ["synth", kind, "--out", str(root), "--split", "validate", "--scenarios", str(group["scenarios"])]
    check(run(args + ["--frames", "10", "--seed", str(group["seeds"][0]), *combo]))
    return [f"{kind}-v4", "--split", "validate"], []


def check(proc: subprocess.CompletedProcess) -> None:
    if proc.returncode != 0:
        raise SystemExit(f"failed: {proc.args[-12:]}\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")


def refusals(out: Path, root: Path, env: dict | None) -> dict[str, list[str]]:
    """Validate every converted log under ``out``: log folder -> the names of its failed checks."""
    with tempfile.NamedTemporaryFile(suffix=".json") as f:
        run(["validate", str(out), "--source", str(root), "--json", f.name], env=env)
        reports = json.loads(Path(f.name).read_text())
    by_log: dict[str, list[str]] = {}
    for r in reports:
        log = Path(r["sequence"]).relative_to(out).parts[0]
        by_log.setdefault(log, []).extend(c["name"] for c in r["checks"] if not c["ok"])
    return by_log


def old_tree(rev: str, work: Path) -> dict:
    """An environment that imports ncore_convert from ``rev`` (a git worktree)."""
    tree = work / f"before-{rev}"
    if not tree.exists():
        subprocess.run(
            ["git", "-C", str(REPO), "worktree", "add", "-f", str(tree), rev], check=True, capture_output=True
        )
    return {**os.environ, "PYTHONPATH": str(tree / "src")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--before", default="bef5368")
    parser.add_argument("--seeds-per-combo", type=int, default=7)
    parser.add_argument("--work", type=Path, default=None)
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench-false-alarms-"))
    before_env = old_tree(args.before, work)
    totals = {"logs": 0, "before": Counter(), "after": Counter(), "refused_before": 0, "refused_after": 0}
    started = time.perf_counter()
    for k, group in enumerate(groups(args.seeds_per_combo)):
        root = work / f"g{k}-{group['name']}{''.join(group['combo'])}"
        if not root.exists():
            command, _ = generate(group, root)
        else:
            command = (
                ["argoverse2-v4", "--split", "val"]
                if group["kind"] == "argoverse2"
                else (["tbv-v4"] if group["kind"] == "tbv" else [f"{group['kind']}-v4", "--split", "validate"])
            )
        for clip in ([], CLIP):
            out = root.with_name(root.name + ("-clip" if clip else "") + "-out")
            if not out.exists():
                check(
                    run(
                        [
                            "--no-progress",
                            "--no-validate",
                            "--root-dir",
                            str(root),
                            "--output-dir",
                            str(out),
                            *command,
                            *clip,
                        ]
                    )
                )
            before, after = refusals(out, root, before_env), refusals(out, root, None)
            totals["logs"] += len(after)
            for name, found in (("before", before), ("after", after)):
                refused = {log: checks for log, checks in found.items() if checks}
                totals[f"refused_{name}"] += len(refused)
                for checks in refused.values():
                    totals[name].update(set(checks))
            print(
                f"{group['name']:7s} {' '.join(group['combo']) or '(defaults)':26s} {'clip' if clip else 'whole':5s}"
                f" logs {len(after):3d}  refused before {sum(bool(c) for c in before.values()):2d}"
                f"  after {sum(bool(c) for c in after.values()):2d}",
                flush=True,
            )
    print(f"\n{totals['logs']} logs in {time.perf_counter() - started:.0f} s (work folder {work})")
    for name in ("before", "after"):
        print(f"refused {name}: {totals[f'refused_{name}']}")
        for check_name, n in totals[name].most_common():
            print(f"  {n:3d}  {check_name}")


if __name__ == "__main__":
    main()
