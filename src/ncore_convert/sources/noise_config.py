"""GPS-error and communication-delay settings (``transforms.noise.NoiseSetting``): OpenCOOD's
``wild_setting`` block, read and checked.

A setting is one named set of parameters (docs/noise.md). It comes
from a YAML file holding a ``wild_setting`` block (an OpenCOOD model YAML works as it is) or from
the equivalent CLI flags. OpenCOOD's own keys keep their names, units and defaults; the keys only
the ``realistic`` model reads are extensions that OpenCOOD ignores.
"""

from __future__ import annotations

import re
from dataclasses import fields

from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.sources.opencood import load_yaml
from ncore_convert.transforms.noise import ASYNC_MODES, DOFS, MODELS, PROCESSES, REALISTIC_ONLY, NoiseSetting

#: OpenCOOD requires these whenever a ``wild_setting`` block is present (basedataset.py).
REQUIRED = ("seed", "async", "async_overhead", "loc_err", "xyz_std", "ryp_std")
#: A setting's name becomes a PosesComponent instance name and generic-data keys.
NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,63}$")


def _key(field_name: str) -> str:
    return "async" if field_name == "async_" else field_name


_TYPES = {_key(f.name): f.type for f in fields(NoiseSetting)}


def _check_value(key: str, value: object) -> object:
    """The value converted to the field's type, or ValueError naming the key and the cause."""
    kind = _TYPES[key]
    if kind == "bool":
        if not isinstance(value, bool):
            raise ValueError(f"{key} must be true or false, not {value!r}")
        return value
    if kind == "int":
        low = 1 if key == "max_cav" else 0
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value < 2**32:
            raise ValueError(f"{key} must be an integer in [{low}, 2**32), not {value!r}")
        return value
    if kind == "float":
        if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 0 or value == float("inf"):
            raise ValueError(f"{key} must be a finite number >= 0, not {value!r}")
        return float(value)
    choices = {"name": None, "model": MODELS, "async_mode": ASYNC_MODES, "process": PROCESSES, "dof": DOFS}[key]
    if choices is None:
        if not isinstance(value, str) or not NAME.match(value) or value == "default":
            raise ValueError(
                f"name must start with a letter and hold only letters, digits, '_' and '-' (at most 64),"
                f" and not be 'default'; got {value!r}"
            )
    elif value not in choices:
        raise ValueError(f"{key} must be one of {', '.join(choices)}, not {value!r}")
    return value


def make_setting(values: dict) -> NoiseSetting:
    """A checked setting from OpenCOOD-named values (``async``, not ``async_``); ValueError with the cause.

    Realistic-only keys with the ``opencood`` model, unknown keys, wrong types, negative numbers and
    a zero transmission speed are errors.
    """
    unknown = sorted(set(values) - set(_TYPES))
    if unknown:
        raise ValueError(f"unknown key(s) {', '.join(map(str, unknown))}; known: {', '.join(sorted(_TYPES))}")
    checked = {key: _check_value(key, value) for key, value in values.items()}
    model = checked.get("model", "opencood")
    extra = [key for key in REALISTIC_ONLY if key in checked]
    if model == "opencood" and extra:
        raise ValueError(f"{', '.join(extra)} only apply to the realistic model (model: realistic)")
    if checked.get("transmission_speed", 27.0) == 0:
        raise ValueError("transmission_speed must be > 0")
    if checked.get("process") == "gauss_markov" and checked.get("correlation_time_s", 10.0) == 0:
        raise ValueError("correlation_time_s must be > 0 for the gauss_markov process")
    return NoiseSetting(**{("async_" if key == "async" else key): value for key, value in checked.items()})


def read_noise_config(path: UPath) -> NoiseSetting:
    """The setting in a YAML file's ``wild_setting`` block (SourceError naming the file and the cause).

    The name is the block's ``name`` key, else the file's stem. As in OpenCOOD, ``seed``, ``async``,
    ``async_overhead``, ``loc_err``, ``xyz_std`` and ``ryp_std`` are required, and ``max_cav`` comes
    from ``train_params`` (default 7).
    """
    data = load_yaml(UPath(path))
    block = data.get("wild_setting")
    if not isinstance(block, dict):
        raise SourceError(path, "no wild_setting mapping (OpenCOOD's GPS-error and delay block)")
    if "rpy_std" in block:  # the spelling in OpenCOOD's README
        raise SourceError(
            path, "wild_setting: OpenCOOD does not read rpy_std (its README's spelling); the key is ryp_std"
        )
    missing = [key for key in REQUIRED if key not in block]
    if missing:
        raise SourceError(path, f"wild_setting lacks {', '.join(missing)} (OpenCOOD requires {', '.join(REQUIRED)})")
    if "max_cav" in block:
        raise SourceError(path, "max_cav belongs in train_params, where OpenCOOD reads it")
    train_params = data.get("train_params") if isinstance(data.get("train_params"), dict) else {}
    values = {"name": UPath(path).stem, **block}
    if "max_cav" in train_params:
        values["max_cav"] = train_params["max_cav"]
    try:
        return make_setting(values)
    except ValueError as err:
        raise SourceError(path, f"wild_setting: {err}") from None


def check_unique(settings: list[NoiseSetting]) -> None:
    """ValueError if two settings share a name (each becomes its own PosesComponent instance)."""
    names = [s.name for s in settings]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f"noise setting name(s) used more than once: {', '.join(repeated)}")
