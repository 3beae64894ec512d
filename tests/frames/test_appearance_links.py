"""Image cameras posting a frame every few seconds: the pose job stores each standing person's appearance, and the
calibration's linking joins one person's sightings by it (real ONNX inference on Town Centre frames)."""

from __future__ import annotations

import csv
from datetime import UTC, datetime, timedelta

import numpy as np
from scipy.optimize import linear_sum_assignment
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from service.calibration import evidence
from service.calibration.service import key_camera_evidence
from service.domain import DONE
from service.geometry.appearance import DESCRIPTOR_BYTES
from service.geometry.tracks import MAX_GAP_S, link_tracks
from service.settings import get_settings
from service.store import Observation
from tests.support.jobs import store_image
from tests.support.shared import TOWN_CENTRE, model_dir_path, require_dir
from workers import jobs

CLIP_FRAMES = (0, 12)  # 0.48 s apart in the clip, posted 2 s apart
SPACING_S = 2.0


def _annotated_identities(frame: int, boxes_px: np.ndarray) -> np.ndarray:
    """The annotated pedestrian (TownCentre-groundtruth.top) each box is, by IoU >= 0.3; -1 for none."""
    annotated = []
    with (TOWN_CENTRE / "TownCentre-groundtruth.top").open() as rows:
        for row in csv.reader(rows):
            if len(row) >= 12 and row[1] == str(frame):
                annotated.append((int(row[0]), [float(v) for v in row[8:12]]))
    truth = np.array([box for _, box in annotated])
    left, top = np.maximum(boxes_px[:, None, 0], truth[None, :, 0]), np.maximum(boxes_px[:, None, 1], truth[None, :, 1])
    right = np.minimum(boxes_px[:, None, 2], truth[None, :, 2])
    bottom = np.minimum(boxes_px[:, None, 3], truth[None, :, 3])
    inter = np.clip(right - left, 0, None) * np.clip(bottom - top, 0, None)
    area = lambda b: (b[..., 2] - b[..., 0]) * (b[..., 3] - b[..., 1])  # noqa: E731
    iou = inter / (area(boxes_px)[:, None] + area(truth)[None, :] - inter)
    rows, cols = linear_sum_assignment(-iou)
    identity = np.full(len(boxes_px), -1)
    for r, c in zip(rows, cols, strict=True):
        if iou[r, c] >= 0.3:
            identity[r] = annotated[c][0]
    return identity


def test_frames_seconds_apart_link_their_people_by_appearance(sessions: sessionmaker[Session]) -> None:
    require_dir(model_dir_path(), "pose model")
    frames_dir = require_dir(TOWN_CENTRE, "Town Centre data") / "frames"
    start = datetime(2026, 1, 1, tzinfo=UTC)
    for k, index in enumerate(CLIP_FRAMES):
        data = (frames_dir / f"clip_{index:06d}.jpg").read_bytes()
        frame_id = store_image(sessions, data, timestamp=start + timedelta(seconds=SPACING_S * k))
        assert jobs.detect_people(str(frame_id)) == DONE
    key_camera_evidence(get_settings(), "town")
    with sessions() as session:
        sample = evidence.sample_evidence(session, "town", cap=2000)
        boxes = {
            o.id: (o.box_left_px, o.box_top_px, o.box_right_px, o.box_bottom_px)
            for o in session.scalars(select(Observation).where(Observation.id.in_(sample.observation_ids)))
        }
    assert len(sample) >= 8 and sorted(set(sample.times_s)) == [0.0, SPACING_S]
    # Usable people found in images are standing ones, and they carry a descriptor unless too little of their body
    # was seen (one of 125 on the 22 clip frames).
    described = [look for look in sample.appearance if look is not None]
    assert len(described) >= 0.8 * len(sample) and all(len(look) == DESCRIPTOR_BYTES for look in described)
    assert SPACING_S > MAX_GAP_S
    plain = link_tracks(sample.times_s, sample.tops_px, sample.bottoms_px)
    assert len(set(plain)) == len(sample)  # motion alone links nobody across 2 s
    labels = link_tracks(sample.times_s, sample.tops_px, sample.bottoms_px, appearance=sample.appearance)
    frame_of = dict(
        zip(sample.observation_ids, (CLIP_FRAMES[round(t / SPACING_S)] for t in sample.times_s), strict=True)
    )
    identity = {}
    for clip_frame in CLIP_FRAMES:
        ids = [oid for oid in sample.observation_ids if frame_of[oid] == clip_frame]
        found = _annotated_identities(clip_frame, np.array([boxes[oid] for oid in ids], dtype=float))
        identity.update(zip(ids, found.tolist(), strict=True))
    linked = [
        (a, b)
        for i, a in enumerate(sample.observation_ids)
        for j, b in enumerate(sample.observation_ids)
        if i < j and labels[i] == labels[j]
    ]
    # Measured: 4 pairs of 14 people linked, each pair one annotated pedestrian.
    assert len(linked) >= 3, linked
    annotated = [(identity[a], identity[b]) for a, b in linked if identity[a] >= 0 and identity[b] >= 0]
    assert len(annotated) >= 3 and all(x == y for x, y in annotated)
