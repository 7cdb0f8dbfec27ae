"""What a check of a converted sequence finds: one :class:`Check` per finding, gathered per file."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field


@dataclass(frozen=True)
class Check:
    name: str
    ok: bool
    detail: str


@dataclass
class Report:
    """The checks of one sequence meta or ``scenario.json`` (``sequence``: its path)."""

    sequence: str
    checks: list[Check] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return all(c.ok for c in self.checks)

    def add(self, name: str, ok: bool, detail: str) -> None:
        self.checks.append(Check(name, bool(ok), detail))

    def to_dict(self) -> dict:
        return {"sequence": self.sequence, "ok": self.ok, "checks": [asdict(c) for c in self.checks]}


def summarise(reports: list[Report]) -> dict:
    """The run report's record of a log's validation: counts and the failed checks, one line each."""
    failed = [f"{r.sequence}: {c.name}: {c.detail}" for r in reports for c in r.checks if not c.ok]
    return {
        "ok": not failed,
        "files": len(reports),
        "checks": sum(len(r.checks) for r in reports),
        "failed": failed,
    }
