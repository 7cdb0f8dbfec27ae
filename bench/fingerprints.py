"""Fingerprints of fixed synthetic conversions: the evidence that a refactor changed no output byte.

Synthesises five fixed sources (AV2, AV2 with the rendered world, TbV, OPV2V, V2XSet), converts them
nine ways (both world modes, ``--lidar-rgb``, f-theta cameras, both layouts, clip windows, noise
settings; validation on) and writes the SHA-256 of every output file (the run report aside: it
holds wall-clock times) and of every source file, one line each, sorted.

    python bench/fingerprints.py --work /tmp/fp-before        # on the old commit
    python bench/fingerprints.py --work /tmp/fp-after         # on the new one
    diff /tmp/fp-before/outputs.sha /tmp/fp-after/outputs.sha
    diff /tmp/fp-before/sources.sha /tmp/fp-after/sources.sha

The AV2 and TbV worlds are pinned to the overlapping traffic the fingerprints were first taken on
(``synth --overlapping-traffic``; before that option existed, the generator's only world), so
fingerprints of commits on either side of the generator's ``--clear-paths`` default compare; the
OPV2V and V2XSet YAMLs to the generator's format before issue 73 (``--legacy-format``); and each
log is written where the other commits write it, whatever ``--out`` means there.
"""

from __future__ import annotations

import argparse
import hashlib
import shutil
import subprocess
import sys
from pathlib import Path

SOURCES = {  #: the AV2 logs are written to <folder>/val
    "av2": ["argoverse2", "--seconds", "1.2", "--seed", "5", "--pictures", "32"],
    "av2r": ["argoverse2", "--seconds", "0.4", "--seed", "6", "--camera-fps", "10", "--world", "render"],
    "tbv": ["tbv", "--seconds", "1.2", "--seed", "7", "--pictures", "32"],
    "opv2v": ["opv2v", "--split", "test", "--frames", "4", "--cavs", "2", "--lidar-columns", "64", "--seed", "3"],
    "v2xset": ["v2xset", "--split", "test", "--frames", "4", "--cavs", "2", "--lidar-columns", "64", "--seed", "8"],
}
#: name -> (source root, command and its options)
CONVERSIONS = {
    "av2": ("av2", ["argoverse2-v4", "--split", "val"]),
    "av2rgb": (
        "av2",
        ["argoverse2-v4", "--split", "val", "--lidar-rgb", "--camera-model", "ftheta", "--profile", "separate-all"],
    ),
    "av2render": ("av2r", ["argoverse2-v4", "--split", "val", "--lidar-rgb"]),
    "tbv": ("tbv", ["tbv-v4"]),
    "tbvrgb": ("tbv", ["tbv-v4", "--lidar-rgb", "--seek-sec", "0.2", "--duration-sec", "0.6"]),
    "opv2v": ("opv2v", ["opv2v-v4", "--split", "test"]),
    "opv2vrgb": ("opv2v", ["opv2v-v4", "--split", "test", "--lidar-rgb", "--layout", "scenario"]),
    "v2xset": (
        "v2xset",
        [
            "v2xset-v4",
            "--split",
            "test",
            "--loc-err",
            "--xyz-std",
            "1",
            "--ryp-std",
            "2",
            "--async",
            "--async-overhead",
            "100",
        ],
    ),
    "v2xsetrgb": (
        "v2xset",
        [
            "v2xset-v4",
            "--split",
            "test",
            "--lidar-rgb",
            "--noise-model",
            "realistic",
            "--loc-err",
            "--layout",
            "scenario",
        ],
    ),
}


def tree_hashes(root: Path, skip: tuple[str, ...] = ()) -> list[str]:
    return [
        f"{hashlib.sha256(p.read_bytes()).hexdigest()}  {p.relative_to(root)}"
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name not in skip
    ]


def pinned_world(cli: str, dataset: str, folder: Path) -> list[str]:
    """``--overlapping-traffic`` and ``--legacy-format`` where this commit's ``synth <dataset>`` has
    them (else its world and files are those), and where it writes: an AV2 log into
    ``<folder>/val``, whether ``--out`` is the dataset root (with ``--split``: since issue 73) or the
    split folder."""
    help_text = subprocess.run([cli, "synth", dataset, "--help"], check=True, capture_output=True, text=True).stdout
    world = [flag for flag in ("--overlapping-traffic", "--legacy-format") if flag in help_text]
    split_folder = dataset == "argoverse2" and "--split" not in help_text
    return [*world, "--out", str(folder / "val" if split_folder else folder)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, required=True, help="folder for the sources, outputs and hash lists")
    args = parser.parse_args()
    cli = str(Path(sys.executable).parent / "ncore-convert")
    sources, outputs = args.work / "sources", args.work / "outputs"
    shutil.rmtree(sources, ignore_errors=True)
    shutil.rmtree(outputs, ignore_errors=True)
    for folder, synth in SOURCES.items():
        pinned = pinned_world(cli, synth[0], sources / folder)
        subprocess.run([cli, "synth", *synth, *pinned], check=True, capture_output=True)
    for name, (source, command) in CONVERSIONS.items():
        run = [cli, "--no-progress", "--workers", "2", "--root-dir", str(sources / source), "--output-dir"]
        subprocess.run([*run, str(outputs / name), *command], check=True, capture_output=True)
    for kind, root, skip in (("outputs", outputs, ("conversion-report.json",)), ("sources", sources, ())):
        lines = tree_hashes(root, skip)
        (args.work / f"{kind}.sha").write_text("\n".join(lines) + "\n")
        print(f"{len(lines)} {kind} hashed: {args.work / f'{kind}.sha'}", flush=True)


if __name__ == "__main__":
    main()
