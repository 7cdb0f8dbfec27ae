"""The documentation keeps up with the command line, and the command line keeps batch logs clean.

- Every option that any command's ``--help`` shows is written in README.md or a file of ``docs/``.
- Without a terminal (CI, batch jobs, ``> log 2>&1``) a conversion prints its per-log lines and no
  progress-bar cursor escapes; ``--progress`` turns the bars on explicitly.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import click
from click.testing import CliRunner
from conftest import BIN, REPO
from upath import UPath

from ncore_convert.cli import cli
from ncore_convert.synth.argoverse2 import SynthConfig, write_log


def documentation() -> str:
    return "\n".join(p.read_text() for p in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))])


def commands(group: click.Group, path: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], click.Command]]:
    """Every command below ``group`` (groups included), with the words that invoke it."""
    out: list[tuple[tuple[str, ...], click.Command]] = [(path, group)]
    for name, command in sorted(group.commands.items()):
        if isinstance(command, click.Group):
            out += commands(command, (*path, name))
        else:
            out.append(((*path, name), command))
    return out


def option_strings(command: click.Command) -> set[str]:
    """The option spellings a command's --help shows (``--x/--no-x`` counts as both)."""
    ctx = click.Context(command, info_name=command.name)
    return {o for p in command.get_params(ctx) if isinstance(p, click.Option) for o in p.opts + p.secondary_opts}


def documented(option: str, text: str) -> bool:
    """``option`` appears as a whole option (``-v`` is not found in ``argoverse2-v4``)."""
    return re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", text) is not None


def test_every_help_option_is_documented():
    text = documentation()
    runner = CliRunner()
    missing, checked = [], set()
    for path, command in commands(cli):
        help_text = runner.invoke(cli, [*path, "--help"]).output
        for option in sorted(option_strings(command)):
            assert option in help_text, f"{' '.join(path) or 'ncore-convert'}: {option} not in --help"
            checked.add(option)
            if not documented(option, text):
                missing.append(f"{' '.join(path) or 'ncore-convert'} {option}")
    assert {"--root-dir", "--noise-config", "--far-range-m", "--swap-lidar-halves", "-v", "--no-maps"} <= checked
    assert missing == []


def test_the_documentation_check_can_fail():
    text = "use `--workers 2` or -v; argoverse2-v4 is a command"
    assert documented("--workers", text) and documented("-v", text)
    assert not documented("--worker", text)  # a prefix of a documented option is not documented
    assert not documented("--no-such-option", documentation())


#: One docs/ file per topic (issue 18): each dataset, the lidar model, TbV timing, noise, validation
#: and preview, scale-out, damaged input, benchmarks, limitations.
TOPICS = (
    "argoverse2",
    "tbv",
    "opv2v-v2xset",
    "lidar-model",
    "tbv-timing",
    "noise",
    "validation",
    "scale-out",
    "damaged-input",
    "benchmarks",
    "limitations",
    "consumers",
    "ego-masks",
)


def test_readme_is_short_and_links_every_topic():
    readme = (REPO / "README.md").read_text()
    assert len(readme.splitlines()) <= 300
    for topic in TOPICS:
        assert (REPO / "docs" / f"{topic}.md").is_file(), topic
        assert f"](docs/{topic}.md)" in readme, f"README does not link docs/{topic}.md"


def test_readme_table_cells_are_short():
    """Every README table cell is at most 40 words: the details live in docs/cli.md and the topic pages."""
    for line in (REPO / "README.md").read_text().splitlines():
        if line.startswith("|"):
            cells = [c for c in line.replace("\\|", "/").strip("|").split("|")]
            assert max(len(c.split()) for c in cells) <= 40, line


def _convert(tmp_path: Path, *flags: str) -> str:
    """Convert a tiny synthetic log through the installed command, stdout and stderr to one pipe."""
    root = tmp_path / "root"
    if not root.exists():
        write_log(UPath(root / "val"), SynthConfig(seconds=0.3, seed=3, camera_fps=0))
    out = tmp_path / f"out{len(flags)}"
    command = [
        str(BIN / "ncore-convert"),
        *flags,
        "--workers",
        "2",
        "--root-dir",
        str(root),
        "--output-dir",
        str(out),
        "argoverse2-v4",
        "--split",
        "val",
    ]
    run = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=600)
    assert run.returncode == 0, run.stdout
    return run.stdout


def test_no_cursor_escapes_without_a_terminal(tmp_path):
    log = _convert(tmp_path)
    assert "\x1b" not in log and "\r" not in log, repr(log)
    assert re.search(r"^ok    \S+: \d+ sweeps", log, flags=re.M), log
    assert "1 converted, 0 skipped, 0 failed" in log
    bars = _convert(tmp_path, "--progress")  # asked for explicitly: the bars are drawn
    assert "\r" in bars or "\x1b[" in bars, repr(bars)


#: The README's names of the dataset commands (its "commands" column).
DATASET_COMMANDS = {"AV2": "argoverse2-v4", "TbV": "tbv-v4", "OPV2V": "opv2v-v4", "V2XSet": "v2xset-v4"}


def _readme_dataset_options() -> list[tuple[list[str], set[str], str]]:
    """The README's "Dataset options" table: per row, its options, the commands it names and the
    row's commands cell."""
    text = (REPO / "README.md").read_text()
    table = text.split("Dataset options:", 1)[1].split("\n\n", 2)[1]
    rows = []
    for line in table.splitlines()[2:]:
        option_cell, commands_cell = (cell.strip() for cell in line.strip("|").split(" | ")[:2])
        groups = [g.strip() for g in commands_cell.split("(")[0].split(" / ")]
        for options_text, group in zip(option_cell.split(" / "), groups * len(option_cell.split(" / ")), strict=False):
            options = re.findall(r"`(--[a-z-]+)", options_text)
            if group.startswith("all but"):
                named = set(DATASET_COMMANDS.values()) - set(re.findall(r"`([a-z0-9-]+)`", group))
            elif group == "all":
                named = set(DATASET_COMMANDS.values())
            else:
                named = {DATASET_COMMANDS[name.strip()] for name in group.split(",")}
            rows.append((options, named, commands_cell))
    return rows


def test_each_dataset_command_offers_what_the_readme_table_says():
    """Each option of the README's dataset-options table is offered by exactly the commands its
    row names, and ``--camera-labels`` offers per command the kinds the row gives (TbV: no
    ``instance``, which needs cuboids)."""
    rows = _readme_dataset_options()
    assert len(rows) >= 20
    offered = {name: option_strings(cli.commands[name]) for name in DATASET_COMMANDS.values()}
    for options, named, cell in rows:
        for option in options:
            having = {name for name, spelled in offered.items() if option in spelled}
            assert having == named, f"README says {option} is for {cell}; --help offers it in {sorted(having)}"
    (labels_cell,) = [cell for options, _, cell in rows if "--camera-labels" in options]
    tbv_kinds = re.search(r"TbV: ([^)]*)\)", labels_cell).group(1)
    expected = {name: "depth,dynamic,instance" for name in DATASET_COMMANDS.values()}
    expected["tbv-v4"] = ",".join(re.findall(r"`([a-z]+)`", tbv_kinds))
    for name, kinds in expected.items():
        help_text = CliRunner().invoke(cli, [name, "--help"]).output
        assert re.search(rf"--camera-labels {kinds}\s", help_text), (name, kinds)
