"""What every dataset converter shares: sensor selection and the counters of a conversion."""

from __future__ import annotations

from dataclasses import fields


def select_sensors(requested: tuple[str, ...] | None, known: tuple[str, ...], kind: str) -> list[str]:
    """Resolve a sensor selection (None = all) against the dataset's sensor names."""
    if requested is None:
        return list(known)
    unknown = sorted(set(requested) - set(known))
    if unknown:
        raise ValueError(f"unknown {kind} id(s) {unknown}; known: {list(known)}")
    return [s for s in known if s in requested]


class Tally:
    """Mixin for counter dataclasses: :meth:`add` adds up (numbers) or concatenates (lists) the
    fields of the dataclass that derives from Tally directly, so its subclasses (a whole-log
    summary, a job result) can carry other fields."""

    def add(self, other: Tally) -> None:
        counted = next(c for c in type(self).__mro__ if Tally in c.__bases__)
        for f in fields(counted):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))
