"""One box per person from the boxes of several detector regions and scales (pure numpy).

The detector's graph already suppresses overlapping boxes within one input, but a frame searched at several
scales or in overlapping tiles sees the same person more than once, and the detector itself sometimes boxes one
person twice in ways IoU cannot catch: a cyclist gets a whole-body box and an upper-body box inside it (IoU ~0.5),
a table of seated people gets one loose box around the group besides each person's own. Rules, in order:

1. Same person, same extent: IoU >= `NMS_IOU` with a more confident box (greedy NMS across regions), whose box
   is kept. The boxes of one person found in different regions are votes, fused into one score:
   1 - prod(1 - best score per region), the chance that not every region is wrong if they erred independently.
   The detector's score for a borderline person swings with scale and crop offset (0.14-0.68 for one man on Town
   Centre), so a person seen at 0.25 at two scales is more credible than one seen once at 0.3: regions pass their
   boxes down to `VOTE_FLOOR`, and the fused score meets the detector's threshold. The regions are not
   independent (the same pixels at another scale and offset), so a box below the floor is no vote: the many
   faint boxes on walls, windows and bollards stay out (two votes at the floor fuse to 0.36, a lone box still
   needs the threshold).
   In a crowd one box can overlap two kept boxes that much: each box votes for the kept box it overlaps most, not
   for the most confident one it overlaps enough (on Town Centre a loose box over a man behind a sign board and
   the man walking past in front of him, 0.63 and 0.51, was the sign-board man's second vote and went to the
   other man). And a person partly hidden behind someone nearer gets both an upper-body box (often the more
   confident) and a whole-body box down to the hidden feet, with IoU >= `NMS_IOU`: when one of a person's votes
   is the whole body of the kept box (rule 2's relation, reaching clearly lower), the person keeps its extent.
2. Same person, partial box: a box lying mostly inside another (`CONTAINED` of its area) and sharing its top
   (within `SHARED_TOP` of the outer box's height) is that person's upper body (cut by a bicycle, a bench, the
   detector's whim). One box is kept, the outer one: it reaches the feet, which the geometry needs. A smaller box
   inside another that does not share its top (a child in front of an adult) is someone else and stays.
3. Group box: a box that contains two or more other boxes, one of them not sharing its top, and is less confident
   than one of them, is a crowd (a table of seated people), not a person. Checked before rule 2, so that the
   people of a group are not merged into its box; a confident box around a person and the child in front of them
   is not a group.
4. Two people one above the other: where it is known how tall a standing person appears with their feet at each
   pixel (a calibration, or the plane of the camera's people: regions.py), a box at least `STACKED` times that
   tall at its feet is not one person's whole body, so rule 1 never gives a person that extent. A Town Centre band
   boxed the man walking past and the man behind the sign board below him at once (299 px where a person stands
   184 px tall); as the upper man's whole body it replaced his own box and covered the hidden man's too.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

import numpy as np

if TYPE_CHECKING:
    from .regions import SizeOf

NMS_IOU: Final = 0.5
VOTE_FLOOR: Final = 0.2
"""Lowest region score that counts as a vote (module docstring). Chosen on Town Centre and the atrium (0.1-0.3 in
docs/benchmarks/pose.md): below 0.2 the boxes matching nobody grow much faster than the people found."""
CONTAINED: Final = 0.8
SHARED_TOP: Final = 0.15
STACKED: Final = 1.45
"""Rule 4: a box this many times the size expected at its feet is not one person (the size plane's worst misses, on
synthetic cameras, are ~1.35; a calibration's are smaller)."""


def iou_matrix(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) intersection over union of xyxy boxes."""
    inter = _intersection(a, b)
    area_a, area_b = _area(a), _area(b)
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-9)


def _area(boxes: np.ndarray) -> np.ndarray:
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    return np.clip(boxes[:, 2] - boxes[:, 0], 0, None) * np.clip(boxes[:, 3] - boxes[:, 1], 0, None)


def _intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    return np.prod(np.clip(rb - lt, 0, None), axis=2)


def inside_fraction(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M): the fraction of each box of `a` that lies inside each box of `b`."""
    return _intersection(a, b) / np.maximum(_area(a)[:, None], 1e-9)


def merge_boxes(
    boxes_xyxy: np.ndarray,
    scores: np.ndarray,
    sources: np.ndarray | None = None,
    *,
    threshold: float = 0.0,
    size_of: SizeOf | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """(boxes, scores) with one box per person (rules in the module docstring), most confident first.

    `sources`: the region each box was found in (default: all in one). A person's score is their votes' fused
    score (rule 1), and only people whose fused score reaches `threshold` are kept; a box below the threshold may
    still be a vote. A partial box's score passes to the outer box it is merged into, so the person keeps the
    detector's best confidence in them. `size_of`: how tall a standing person appears with their feet at each pixel
    (NaN where unknown), for rule 4; without it, rule 4 does not apply.
    """
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    sources = np.zeros(len(scores), dtype=np.int64) if sources is None else np.asarray(sources).reshape(-1)
    order = np.argsort(-scores, kind="stable")
    boxes, scores, sources = boxes[order], scores[order], sources[order]
    overlap = iou_matrix(boxes, boxes)
    kept: list[int] = []  # greedy NMS: a box overlapping a more confident kept box is not a person of its own
    for i in range(len(boxes)):
        if not any(overlap[i, j] >= NMS_IOU for j in kept):
            kept.append(i)
    votes: list[dict[int, float]] = [{} for _ in kept]  # per kept box: its region -> the best score there
    members: list[list[int]] = [[] for _ in kept]
    for i in range(len(boxes)):
        # A box votes for the kept box it overlaps most, not the first (most confident) it overlaps enough: in a
        # crowd one loose box overlaps two people, and it is the evidence for the one it fits.
        near = overlap[i, kept]
        leader = int(np.argmax(near))
        if near[leader] < NMS_IOU:
            continue
        votes[leader][int(sources[i])] = max(votes[leader].get(int(sources[i]), 0.0), float(scores[i]))
        members[leader].append(i)
    fused = np.array([1.0 - np.prod([1.0 - v for v in vote.values()]) for vote in votes])
    stacked = _stacked(boxes, size_of)
    extent = np.array([_whole_body(boxes, k, members[n], stacked) for n, k in enumerate(kept)], dtype=np.int64)
    chosen = fused >= threshold
    boxes, scores = boxes[extent][chosen], fused[chosen]
    order = np.argsort(-scores, kind="stable")
    boxes, scores = boxes[order], scores[order]

    inside = inside_fraction(boxes, boxes)  # [i, j]: share of box i inside box j
    np.fill_diagonal(inside, 0.0)
    contains = inside >= CONTAINED
    heights = boxes[:, 3] - boxes[:, 1]
    shares_top = np.abs(boxes[:, None, 1] - boxes[None, :, 1]) <= SHARED_TOP * heights[None, :]
    # kept is in score order, so a box containing a more confident box holds it at a lower index.
    more_confident = np.tril(np.ones((len(boxes), len(boxes)), dtype=bool), -1).T
    groups = (contains.sum(axis=0) >= 2) & (contains & ~shares_top).any(axis=0) & (contains & more_confident).any(0)
    partial = contains & shares_top & ~groups[None, :]
    drop = groups.copy()
    for i in np.argsort(heights, kind="stable"):  # smallest first: a partial box merges into its outer box
        outer = np.flatnonzero(partial[i] & ~drop)
        if len(outer) and not drop[i]:
            drop[i] = True
            target = outer[np.argmax(heights[outer])]
            scores[target] = max(scores[target], scores[i])
    keep = ~drop
    boxes, scores = boxes[keep], scores[keep]
    order = np.argsort(-scores, kind="stable")
    return boxes[order], scores[order]


def _stacked(boxes: np.ndarray, size_of: SizeOf | None) -> np.ndarray:
    """(N,) rule 4: boxes too tall to be one person standing where their feet are."""
    if size_of is None or not len(boxes):
        return np.zeros(len(boxes), dtype=bool)
    expected = np.asarray(size_of(np.c_[(boxes[:, 0] + boxes[:, 2]) / 2.0, boxes[:, 3]]), dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return (boxes[:, 3] - boxes[:, 1]) >= STACKED * expected


def _whole_body(boxes: np.ndarray, leader: int, members: list[int], stacked: np.ndarray) -> int:
    """The box one person's votes keep: the most confident, unless a vote is the same person's whole body.

    A person partly hidden behind someone nearer is boxed by the detector both to their visible upper body
    (often the more confident box) and to their whole body down to the hidden feet; the two overlap with IoU
    >= `NMS_IOU`, so rule 1 sees them as one person and would keep the upper body. Rule 2 prefers the outer box of
    a same-top pair, because the feet are what the geometry measures from; this keeps that preference when the
    pair overlaps that much. A vote counts as the whole body when it holds the kept box (`CONTAINED`), shares its
    top (`SHARED_TOP` of its own height) and reaches clearly lower (its bottom more than `SHARED_TOP` of its
    height below), so a same-extent jitter never moves the box; of several, the most confident (lowest index). A box
    too tall to be one person (`stacked`, rule 4) is no one's whole body.
    """
    top_px, bottom_px = boxes[leader, 1], boxes[leader, 3]
    for i in sorted(members):
        outer = boxes[i]
        outer_height_px = outer[3] - outer[1]
        if (
            i != leader
            and not stacked[i]
            and inside_fraction(boxes[leader], outer)[0, 0] >= CONTAINED
            and abs(outer[1] - top_px) <= SHARED_TOP * outer_height_px
            and outer[3] - bottom_px > SHARED_TOP * outer_height_px
        ):
            return i
    return leader
