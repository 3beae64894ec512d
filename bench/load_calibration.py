"""How fresh the calibrations stay under load: the time from a camera becoming due a solve to that solve.

A camera is *due* once its usable evidence reaches the service's target for the next solve (what
`GET .../calibration` reports as `evidence_count` + `people_needed`; the rule is the service's,
service.calibration.service.evidence_for_next_solve). It is *solved* when the next version (any outcome) is
stored, at its `created_at`. The dashboards' polls see each camera every couple of seconds; the moment evidence
crossed the target is interpolated between the last poll below it and the first at or above it (evidence grows
steadily while people walk), so the figure does not carry the polling interval. The solves come from each
camera's history, read once after the drain.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass, field
from datetime import datetime


@dataclass
class Poll:
    wall_s: float
    evidence: int
    needed: int


@dataclass
class Freshness:
    """Due-to-solved seconds of the solves that fell due in the window, and the ones still unsolved at the end."""

    solved_s: list[float] = field(default_factory=list)
    unsolved_waited_s: list[float] = field(default_factory=list)  # due in the window, no solve by the end
    solves_in_window: int = 0


class CalibrationWatch:
    """Keeps the dashboards' calibration polls per camera and turns them, with the histories, into Freshness."""

    def __init__(self) -> None:
        self.polls: dict[str, list[Poll]] = {}

    def record(self, camera_id: str, wall_s: float, body: bytes) -> None:
        status = json.loads(body)
        self.polls.setdefault(camera_id, []).append(
            Poll(wall_s, int(status["evidence_count"]), int(status["people_needed"]))
        )

    def due_times(self, camera_id: str) -> list[tuple[float, float]]:
        """When the camera fell due, one (not due yet, due) pair of wall times per episode: the last poll that saw it
        not due, and the moment interpolated between that poll and the next. A camera already due at its first poll
        counts as due then (both times): a lower bound on its wait."""
        polls = self.polls.get(camera_id, [])
        times = [(polls[0].wall_s, polls[0].wall_s)] if polls and polls[0].needed <= 0 else []
        for before, after in itertools.pairwise(polls):
            if before.needed <= 0:
                continue  # already due: the episode began earlier
            target = before.evidence + before.needed
            if after.evidence < target:
                continue
            grown = after.evidence - before.evidence
            fraction = (target - before.evidence) / grown if grown > 0 else 1.0
            times.append((before.wall_s, before.wall_s + min(max(fraction, 0.0), 1.0) * (after.wall_s - before.wall_s)))
        return times

    def freshness(self, solved_at: dict[str, list[float]], window: tuple[float, float], end_s: float) -> Freshness:
        """`solved_at`: each camera's solve times (wall). An episode counts when it overlaps the window: due before
        its end and not solved before its start (a camera still waiting when the window opens counts, with the
        whole of its wait). `end_s`: when the histories were read (an episode still open then waited until it).

        An episode's solve is the first stored after the last poll that saw the camera not due: the service asks
        for the solve the moment the evidence is stored, so a solve can land between two polls before the
        interpolated due time (evidence arrives in bursts, not evenly), and pairing it with the next solve would
        count the episode as unsolved. An unforced solve runs only once its camera is due, so the evidence crossed
        the target between that poll and the solve: the episode counts the whole of that span (an upper bound)."""
        result = Freshness()
        start, stop = window
        for camera_id, solves in solved_at.items():
            result.solves_in_window += sum(start <= t < stop for t in solves)
            for not_due, due in self.due_times(camera_id):
                after = [t for t in solves if t >= not_due]
                solved = min(after) if after else None
                if due >= stop or (solved is not None and solved < start):
                    continue
                if solved is not None:
                    result.solved_s.append(solved - due if solved >= due else solved - not_due)
                else:
                    result.unsolved_waited_s.append(end_s - due)
        return result


def solve_times(history_body: bytes) -> list[float]:
    """The wall times of a camera's stored solves, from `GET .../calibration/history`."""
    return [datetime.fromisoformat(item["created_at"]).timestamp() for item in json.loads(history_body)["items"]]
