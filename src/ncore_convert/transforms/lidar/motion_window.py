"""Movers carried between sweeps, and the window of sweeps a log streams through (docs/motion.md):
each sweep is flagged against the sweeps ``OFFSETS`` away (``free_space.flag_sweep``), then takes the
objects that continue a mover of the sweep before or after it (:func:`follow`)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from ncore_convert.transforms.lidar.free_space import SweepFlags, SweepSight, flag_sweep

#: An object of one sweep is the mover flagged in the sweep before or after it when this share of its
#: returns lie within ``FOLLOW_M`` of that mover's returns (a car at 15 m/s moves 1.5 m a sweep:
#: most of its sides stay within a metre of where they were).
FOLLOW_SHARE = 0.5
FOLLOW_M = 1.0
#: ... unless it is settled (``free_space.SETTLED_SHARE``).
#: Every this many of a mover's returns stand for it (they lie centimetres apart; a metre is asked).
FOLLOW_STRIDE = 4


def follow(flags: SweepFlags, reference: SweepFlags) -> np.ndarray:
    """The objects of ``flags`` that continue a mover of ``reference`` (the sweep before or after),
    as flags on ``flags``' returns, bool [N]. A mover the lidar never saw through in its own sweep
    (a car driving ahead at the ego's speed hides its own trail from every earlier sweep) is found
    from the sweeps that did."""
    movers = reference.points_m[reference.dynamic][::FOLLOW_STRIDE]
    n = len(flags.followable)
    if not len(movers) or not n:
        return np.zeros(len(flags.objects), bool)
    sample = flags.samples
    xyz_m = flags.points_m[sample]
    distance, _ = cKDTree(movers).query(xyz_m, distance_upper_bound=FOLLOW_M)
    hit = np.isfinite(distance)
    objects_sampled = flags.objects[sample]
    share = np.bincount(objects_sampled, hit, n) / np.maximum(np.bincount(objects_sampled, minlength=n), 1)
    carried = (share >= FOLLOW_SHARE) & flags.followable
    return (flags.objects >= 0) & carried[np.maximum(flags.objects, 0)] & ~flags.settled


#: The sweeps each sweep is tested against, by their distance in sweeps (a slow mover needs the far
#: ones: 0.5 m/s moves 0.4 m in 0.8 s; a log of two sweeps has only the next one). The sweeps 2 and 4
#: away added nothing on the held-out seeds (SA 0.9987 -> 0.9991, the same DA, without them).
OFFSETS = (-8, -3, -1, 1, 3, 8)


class MotionWindow:
    """Flags a log's sweeps as they stream (:meth:`push` each sweep's units, then :meth:`finish`).

    Each sweep is tested against the sweeps ``OFFSETS`` away (:func:`flag_sweep`), then takes the
    objects that continue a mover the sweep before or after it found (:func:`follow`, one hop: a
    chain would carry a static object flagged once through the rest of the log). Within
    ``max(OFFSETS)`` sweeps of the log's ends, where a sweep has others on one side only, the movers
    are carried along a chain from the first (and the last) sweep with others on both sides: a car
    driving ahead at the ego's speed hides its own trail from every earlier sweep, so the last
    sweeps see nothing of it move. Holds ``2 * max(OFFSETS) + 1`` sweeps: memory does not grow with
    the log."""

    def __init__(self) -> None:
        self._sights: dict[int, list[SweepSight]] = {}
        self._found: dict[int, SweepFlags] = {}
        self._last: SweepFlags | None = None  # the flags last handed out
        self._next = 0  # the next sweep to hand out
        self._pushed = 0

    def push(self, units: list[SweepSight]) -> list[tuple[int, SweepFlags]]:
        """Add the next sweep; returns the sweeps now final: (index, flags), in order."""
        self._sights[self._pushed] = units
        self._pushed += 1
        return self._advance(final=False)

    def finish(self) -> list[tuple[int, SweepFlags]]:
        """The remaining sweeps' flags, in order."""
        return self._advance(final=True)

    def _advance(self, final: bool) -> list[tuple[int, SweepFlags]]:
        reach = max(OFFSETS)
        start = max(self._found) + 1 if self._found else 0
        for k in range(start, self._pushed):
            if k + reach < self._pushed or final:
                others = [self._sights[k + d] for d in OFFSETS if 0 <= k + d < self._pushed]
                far = [self._sights[k + d] for d in (-reach, reach) if 0 <= k + d < self._pushed]
                self._found[k] = flag_sweep(self._sights[k], others, far)
        ready = []
        while self._ready(self._next, final):
            k = self._next
            flags = self._found[k]
            dynamic = flags.dynamic.copy()
            if k < reach:  # the head: carried back from the first sweep with others on both sides
                top = min(reach, max(self._found))
                carried = self._found[top]
                for j in range(top - 1, k - 1, -1):
                    found = self._found[j]
                    carried = replace(found, dynamic=found.dynamic | follow(found, carried))
                dynamic |= carried.dynamic
            elif k + 1 in self._found:  # one hop from the sweep after it
                dynamic |= follow(flags, self._found[k + 1])
            if self._last is not None:
                tail = final and k >= self._pushed - reach
                dynamic |= follow(flags, self._last if tail else self._found[k - 1])  # the tail: a chain
            self._last = replace(flags, dynamic=dynamic)
            ready.append((k, self._last))
            self._next += 1
            self._found.pop(k - 1, None)
            self._sights.pop(k - reach, None)
        return ready

    def _ready(self, k: int, final: bool) -> bool:
        """Whether sweep ``k`` can be handed out: its flags and the next sweep's are known (in the
        head, those up to the first sweep with others on both sides)."""
        if k not in self._found:
            return False
        return final or max(k + 1, max(OFFSETS)) in self._found
