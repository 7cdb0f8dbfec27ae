"""The command line's answers to a user's mistakes: usage errors (exit 2) that name the fix, and
group options accepted after the dataset command.

- :class:`DatasetCommand`: a dataset command whose usage line and help show the group options
  (``--root-dir``, ``--output-dir``, ``--workers``, ...), which come before it.
- :class:`ConverterGroup` (:func:`hoist_group_options`): a group option given after the dataset
  command is moved before it (the same effect as written there), instead of "No such option" and
  an unrelated suggestion.
- :func:`wrong_root`: what ``--root-dir`` is when it is not the command's dataset root (the split
  folder, one log, another dataset's tree), and what to give instead.
- :func:`pick_ids`, :func:`make_output`: the requested ids, or the ones that exist; the output
  folder, or why it cannot be.
"""

from __future__ import annotations

import os
import tempfile

import click
from upath import UPath

from ncore_convert.paths import is_local
from ncore_convert.sources import layout

#: The dataset commands whose unit is a scenario (the others' is a log).
OPENCOOD_COMMANDS = ("opv2v-v4", "v2xset-v4")
GROUP_USAGE = "--root-dir R --output-dir O [GROUP OPTIONS]"


class ConverterGroup(click.Group):
    """``ncore-convert``: group options given after a dataset command are moved before it."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        return super().parse_args(ctx, hoist_group_options(self, ctx, args))


class DatasetCommand(click.Command):
    """A dataset command: its usage line and help say that the group options come first."""

    def format_usage(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        program = ctx.parent.info_name if ctx.parent is not None else "ncore-convert"
        formatter.write_usage(f"{program} {GROUP_USAGE}", f"{self.name} {' '.join(self.collect_usage_pieces(ctx))}")

    def format_epilog(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        formatter.write_paragraph()
        formatter.write_text(
            "Group options (--root-dir, --output-dir, --workers, --executor, --camera-id, --no-validate, ...; see"
            " 'ncore-convert --help') come before the command; given after it, they are moved there."
        )


def _arity(group: click.Group, ctx: click.Context) -> dict[str, int]:
    """Each group option spelling and how many values follow it."""
    out = {}
    for param in group.get_params(ctx):
        if isinstance(param, click.Option):
            takes = 0 if (param.is_flag or param.count) else param.nargs
            out.update(dict.fromkeys(param.opts + param.secondary_opts, takes))
    return out


def hoist_group_options(group: click.Group, ctx: click.Context, args: list[str]) -> list[str]:
    """``args`` with the group options that follow a dataset command moved before it (with their
    values), where they mean what they mean there; options of the command itself, and everything
    after ``--``, stay. Other commands' arguments are left alone."""
    arity = _arity(group, ctx)
    for own_meaning in (*ctx.help_option_names, "--version"):  # the command's help is its own
        arity.pop(own_meaning, None)
    at = 0
    while at < len(args) and args[at].startswith("-"):  # the group options before the command
        name = args[at].split("=", 1)[0]
        at += 1 + (arity.get(name, 0) if "=" not in args[at] else 0)
    command = group.commands.get(args[at]) if at < len(args) else None
    if not isinstance(command, DatasetCommand):
        return args
    own = {o for p in command.params if isinstance(p, click.Option) for o in p.opts + p.secondary_opts}
    moved, kept, k = [], [], at + 1
    while k < len(args):
        token = args[k]
        if token == "--":
            kept += args[k:]
            break
        name = token.split("=", 1)[0]
        if name in arity and name not in own:
            width = 1 + (arity[name] if "=" not in token else 0)
            moved += args[k : k + width]
            k += width
        else:
            kept.append(token)
            k += 1
    return [*args[:at], *moved, args[at], *kept]


def _fix(command: str, root: UPath, kind: str, first: str | None) -> str | None:
    """What to give instead of ``root`` (``kind``: what it is, :func:`layout.kind_of`), or None."""
    parent = root.parent
    if command in OPENCOOD_COMMANDS:
        if kind == layout.SCENARIOS:
            return f"it is the split folder itself: give its parent, --root-dir {parent}"
        if kind == layout.SCENARIO:
            return f"it is one scenario's folder: give --root-dir {parent.parent} --scenario {root.name}"
        if kind in (layout.AV2_LOG, layout.AV2_LOGS, layout.AV2_SPLITS):
            return "convert it with argoverse2-v4 (tbv-v4 for a TbV root)"
        return None
    if kind in (layout.SCENARIO, layout.SCENARIOS, layout.OPENCOOD_SPLITS):
        return "convert it with opv2v-v4 or v2xset-v4"
    if kind == layout.AV2_LOG:
        where = parent if command == "tbv-v4" else parent.parent
        return f"it is one log's folder: give --root-dir {where} --log-id {root.name}"
    if command == "argoverse2-v4" and kind == layout.AV2_LOGS:
        if first is not None and layout.is_tbv_log_id(first):
            return "it holds TbV logs: convert it with tbv-v4"
        return f"it is the split folder itself: give its parent, --root-dir {parent}"
    if command == "tbv-v4" and kind == layout.AV2_SPLITS:
        return "it holds split folders: convert it with argoverse2-v4 --split <split>"
    return None


def wrong_root(command: str, root: UPath) -> str | None:
    """Why ``root`` is not ``command``'s dataset root and what to give instead (one line), or None
    when its layout says nothing (a few listings: called on a failed or suspicious listing only)."""
    kind, first = layout.kind_of(root)
    fix = None if kind is None else _fix(command, root, kind, first)
    return None if fix is None else f"--root-dir {root} is {kind}: {fix}"


def unit_is_wrong(command: str, unit_dir: UPath) -> bool:
    """Whether the first listed log or scenario folder is plainly another kind of folder (another
    dataset's tree, a split folder given as the root); one that is merely damaged is not (it
    fails as a log): a listing or two."""
    want = layout.SCENARIO if command in OPENCOOD_COMMANDS else layout.AV2_LOG
    kind, _ = layout.kind_of(unit_dir)
    return kind is not None and kind != want


def ids_hint(available: list[str], noun: str, shown: int = 5) -> str:
    """The ids that exist, for a message: a few of them and how many."""
    if not available:
        return f"there are no {noun}s there"
    more = f" ... ({len(available)} in all)" if len(available) > shown else ""
    return f"there: {', '.join(available[:shown])}{more}"


def make_output(out: UPath) -> None:
    """Create the output folder (and its parents) or say why it cannot be, as a usage error naming
    ``--output-dir`` (a file in the way, a system folder, no permission). A bucket needs no folder."""
    if not is_local(out):
        return
    try:
        out.mkdir(parents=True, exist_ok=True)
        os.rmdir(tempfile.mkdtemp(dir=out.path, prefix=".ncore-convert-probe-"))  # writable, not only there
    except OSError as err:
        why = {
            FileExistsError: "a file is in the way",
            NotADirectoryError: "a file is in the way",
            PermissionError: "permission denied",
        }.get(type(err), err.strerror or type(err).__name__)
        raise click.UsageError(
            f"--output-dir {out}: the output folder cannot be made ({why}); give a folder you can write"
        ) from None


def pick_ids(requested: tuple[str, ...], available: list[str], where: UPath, noun: str) -> list[str]:
    """The requested logs (or scenarios) in order, all available ones if none are requested."""
    if requested:
        unknown = [name for name in requested if name not in available]
        if unknown:
            there = ids_hint(available, noun)
            raise click.UsageError(f"{noun}(s) not found under {where}: {', '.join(unknown)}; {there}")
        return list(dict.fromkeys(requested))
    if not available:
        raise click.UsageError(f"no {noun}s under {where}")
    return available
