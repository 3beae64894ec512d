"""Which violating pairs deserve a `violation.detected` alert: one lingering pair must not fire on every frame.

People carry no identity across frames, so "the same pair" is decided by where its two people stand:

    A violating pair in a frame at time t is the same as an alerted pair when both of its people stand within
    `radius_m` (on the ground) of the alerted pair's two people as last seen, in either order, and
    |t - alert time| < `window_s`. The same pair raises no alert, but its last-seen positions move to where it
    stands now, so two people walking together stay one pair. Once `window_s` has passed since its alert, a
    pair that is still there alerts again (a pair standing still fires once per window). A pair elsewhere in
    the camera, or with one of its people elsewhere, alerts at once.

Pairs alerted in the same frame never silence each other: three people in a huddle raise all three pairs.
Frame time (the client's timestamp) is used, not arrival time, so frames measured late (a backlog answered by a
first calibration) are judged as they happened. No I/O: the store loads and saves the alerted pairs.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime, timedelta

Ground = tuple[float, float]


@dataclass
class AlertedPair:
    """A pair that raised an alert at `alerted_at`; `row_id` is its stored row (None until saved)."""

    alerted_at: datetime
    a: Ground
    b: Ground
    row_id: int | None = None
    moved: bool = False
    """Its last-seen positions changed since it was loaded (the store must write them back)."""


@dataclass(frozen=True)
class Candidate:
    """A violating pair of one frame: indices into the frame's people and their ground positions (metres)."""

    i: int
    j: int
    a: Ground
    b: Ground


def _near(p: Ground, q: Ground, radius_m: float) -> bool:
    return math.hypot(p[0] - q[0], p[1] - q[1]) <= radius_m


def _match_cost(pair: AlertedPair, candidate: Candidate, radius_m: float) -> tuple[float, bool] | None:
    """(total displacement, swapped) when the candidate is within radius of the pair in some order, else None."""
    best = None
    for swapped, (a, b) in ((False, (candidate.a, candidate.b)), (True, (candidate.b, candidate.a))):
        if _near(pair.a, a, radius_m) and _near(pair.b, b, radius_m):
            cost = math.dist(pair.a, a) + math.dist(pair.b, b)
            if best is None or cost < best[0]:
                best = (cost, swapped)
    return best


class Cooldown:
    """The alerted pairs of one camera, and the rule above applied to frames in turn."""

    def __init__(self, alerted: Iterable[AlertedPair], *, window_s: float, radius_m: float) -> None:
        self.alerted = list(alerted)
        self.window_s = window_s
        self.radius_m = radius_m

    def admit(self, at: datetime, candidates: Iterable[Candidate]) -> list[Candidate]:
        """The frame's pairs that raise an alert; the others refresh the positions of the pair they match."""
        earlier = list(self.alerted)
        fired: list[Candidate] = []
        for candidate in candidates:
            match = None
            if self.window_s > 0:
                best = None
                for pair in earlier:
                    if abs((at - pair.alerted_at).total_seconds()) >= self.window_s:
                        continue
                    found = _match_cost(pair, candidate, self.radius_m)
                    if found is not None and (best is None or found[0] < best[0]):
                        best, match = found, (pair, found[1])
            if match is None:
                fired.append(candidate)
                self.alerted.append(AlertedPair(at, candidate.a, candidate.b))
                continue
            pair, swapped = match
            pair.a, pair.b = (candidate.b, candidate.a) if swapped else (candidate.a, candidate.b)
            pair.moved = True
        return fired

    def expired_before(self, at: datetime) -> datetime:
        """Alerts older than this can no longer silence a frame at `at` or later."""
        return at - timedelta(seconds=self.window_s)
