"""What one `posemetry analyze` run found, as the writers, the pictures and the summary read it: the frames' people,
the pooled evidence, the solve and the tallies; and the `Observer` a run reports its progress to.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal, Protocol

import numpy as np

from service.domain import PersonIn
from service.frames.schemas import FrameResult
from service.geometry import Calibration
from service.geometry.evidence import EvidenceSolve

from .options import AnalyzeOptions
from .records import CalibrationRole
from .sources import FrameSource, SkippedFrame

Stage = Literal["pose", "guided", "calibration", "results"]


class Observer(Protocol):
    """What a run reports while it works (the command shows it as progress bars)."""

    def begin(self, stage: Stage, total: int | None) -> None: ...

    def advance(self, people: int = 0) -> None: ...

    def note(self, message: str) -> None: ...


@dataclass(frozen=True)
class AnalyzedFrame:
    """A frame's people as the pose model found them."""

    index: int
    time_s: float | None
    file: str | None
    people: list[PersonIn]


@dataclass(frozen=True)
class Evidence:
    """The usable people of all frames, pooled: shoulder and ankle centres, and whose they are."""

    tops_px: np.ndarray
    bottoms_px: np.ndarray
    owners: list[tuple[int, int]]
    """(position in the frame list, person index) of each row."""
    appearance: list[bytes | None] = field(default_factory=list)
    """Each row's appearance descriptor (service.geometry.appearance): links one person across frames seconds
    apart (images, a large --stride)."""

    @classmethod
    def of(cls, frames: Sequence[AnalyzedFrame]) -> Evidence:
        tops, bottoms, owners, appearance = [], [], [], []
        for position, frame in enumerate(frames):
            for index, person in enumerate(frame.people):
                if person.unusable_reason is None and person.shoulder_px is not None and person.ankle_px is not None:
                    tops.append(person.shoulder_px)
                    bottoms.append(person.ankle_px)
                    owners.append((position, index))
                    appearance.append(person.appearance)
        return cls(
            np.array(tops, dtype=float).reshape(-1, 2),
            np.array(bottoms, dtype=float).reshape(-1, 2),
            owners,
            appearance,
        )

    def __len__(self) -> int:
        return len(self.owners)


@dataclass
class Analysis:
    """Everything a run found: what the writers and the summary need."""

    source: FrameSource
    options: AnalyzeOptions
    pose_model: str
    frames: list[AnalyzedFrame]
    skipped: list[SkippedFrame]
    evidence: Evidence
    solve: EvidenceSolve
    roles: dict[tuple[int, int], CalibrationRole] = field(default_factory=dict)
    """(frame position, person index) -> the person's part in the calibration (usable people only)."""
    times_s: dict[str, float] = field(default_factory=dict)
    """Seconds per stage: pose, calibration, results (measuring and writing tables and pictures)."""
    warnings: list[str] = field(default_factory=list)
    violations: int = 0
    """Pairs under the threshold, over all frames (counted as frames are measured)."""
    frames_with_violations: int = 0
    people_placed: int = 0

    @property
    def calibration(self) -> Calibration | None:
        return self.solve.calibration

    @property
    def people_seen(self) -> int:
        return sum(len(frame.people) for frame in self.frames)

    def unusable_reasons(self) -> dict[str, int]:
        counts = Counter(p.unusable_reason for f in self.frames for p in f.people if p.unusable_reason is not None)
        return dict(counts.most_common())

    @property
    def wants_video(self) -> bool:
        """Overlay videos: asked for, or by default for a video input."""
        wanted = self.options.write_video
        return self.source.kind == "video" if wanted is None else wanted

    def tally(self, result: FrameResult) -> None:
        self.violations += len(result.violations)
        self.frames_with_violations += bool(result.violations)
        self.people_placed += sum(person.ground_m is not None for person in result.people)
