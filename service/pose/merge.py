"""One box per person from the boxes of several detector regions and scales (pure numpy).

The detector's graph already suppresses overlapping boxes within one input, but a frame searched at several
scales or in overlapping tiles sees the same person more than once, and the detector itself sometimes boxes one
person twice in ways IoU cannot catch: a cyclist gets a whole-body box and an upper-body box inside it (IoU ~0.5),
a table of seated people gets one loose box around the group besides each person's own. Rules, in order:

1. Same person, same extent: IoU >= `NMS_IOU` with a more confident box (greedy NMS across regions).
2. Same person, partial box: a box lying mostly inside another (`CONTAINED` of its area) and sharing its top
   (within `SHARED_TOP` of the outer box's height) is that person's upper body (cut by a bicycle, a bench, the
   detector's whim). One box is kept, the outer one: it reaches the feet, which the geometry needs. A smaller box
   inside another that does not share its top (a child in front of an adult) is someone else and stays.
3. Group box: a box that contains two or more other boxes, one of them not sharing its top, and is less confident
   than one of them, is a crowd (a table of seated people), not a person. Checked before rule 2, so that the
   people of a group are not merged into its box; a confident box around a person and the child in front of them
   is not a group.
"""

from __future__ import annotations

from typing import Final

import numpy as np

NMS_IOU: Final = 0.5
CONTAINED: Final = 0.8
SHARED_TOP: Final = 0.15


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


def merge_boxes(boxes_xyxy: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(boxes, scores) with one box per person (rules in the module docstring), most confident first.

    A partial box's score passes to the outer box it is merged into, so the person keeps the detector's best
    confidence in them.
    """
    boxes = np.asarray(boxes_xyxy, dtype=np.float64).reshape(-1, 4)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    order = np.argsort(-scores, kind="stable")
    boxes, scores = boxes[order], scores[order]
    iou = iou_matrix(boxes, boxes)
    kept: list[int] = []
    for i in range(len(boxes)):
        if all(iou[i, j] < NMS_IOU for j in kept):
            kept.append(i)
    boxes, scores = boxes[kept], scores[kept].copy()

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
