"""What a person looks like, from the frame's pixels: the appearance descriptor of service.geometry.appearance.

Calibration links one person's observations into one individual (service.geometry.tracks) so that their height
counts once. Positions and times link frames a fraction of a second apart; a camera that posts one image every
few seconds needs to know that the person in dark trousers and a red coat now is the one seen two seconds ago,
and only the frame's pixels say so. They are at hand only here, in the image pipeline: the descriptor is stored
with the observation, the pixels are not.

Regions come from the person's keypoints, so they follow the body rather than the box (a box holds background
and neighbours): the torso is the quadrilateral of shoulders and hips, shrunk by TORSO_SHRINK towards its centre
(the outline is where the background bleeds in), and the legs are each hip-knee-ankle polyline drawn
LEG_WIDTH_FRACTION of the shoulder-to-ankle length wide. Pixels inside the box of a person in front (their box
reaches lower in the frame) are left out: they are that person's coat. A region with fewer than
MIN_REGION_PIXELS pixels left gives no descriptor (a colour histogram of a handful of pixels matches anything).
"""

from __future__ import annotations

import cv2
import numpy as np

from service.geometry.appearance import APPEARANCE_BINS, encode_descriptor

SHOULDERS, HIPS, KNEES, ANKLES = (5, 6), (11, 12), (13, 14), (15, 16)
MIN_SCORE = 0.3
TORSO_SHRINK = 0.15
LEG_WIDTH_FRACTION = 0.06
MIN_REGION_PIXELS = 30
_HSV_RANGES = [0, 180, 0, 256, 0, 256]


def appearance_descriptor(
    image_bgr: np.ndarray,
    keypoints_px: np.ndarray,
    keypoint_scores: np.ndarray,
    box_xyxy_px: np.ndarray,
    front_boxes_xyxy_px: np.ndarray,
) -> bytes | None:
    """The person's descriptor (service.geometry.appearance), or None when shoulders, hips or a leg are not seen
    (score MIN_SCORE) or a region keeps too few pixels. `front_boxes_xyxy_px`: (m, 4) boxes of people in front."""
    points, scores = np.asarray(keypoints_px, dtype=np.float64), np.asarray(keypoint_scores, dtype=np.float64)
    needed = SHOULDERS + HIPS
    if np.any(scores[list(needed)] < MIN_SCORE):
        return None
    legs = [(hip, knee, ankle) for hip, knee, ankle in zip(HIPS, KNEES, ANKLES, strict=True)]
    legs = [leg for leg in legs if np.all(scores[list(leg)] >= MIN_SCORE)]
    if not legs:
        return None
    height, width = image_bgr.shape[:2]
    used = np.vstack([points[list(needed)], *(points[list(leg)] for leg in legs), np.reshape(box_xyxy_px, (2, 2))])
    left, top = np.clip(np.floor(used.min(axis=0)).astype(int) - 2, 0, None)
    right, bottom = np.minimum(np.ceil(used.max(axis=0)).astype(int) + 3, (width, height))
    if right - left < 2 or bottom - top < 2:
        return None
    hsv = cv2.cvtColor(np.ascontiguousarray(image_bgr[top:bottom, left:right]), cv2.COLOR_BGR2HSV)
    origin = np.array([left, top], dtype=np.float64)
    torso = points[[SHOULDERS[0], SHOULDERS[1], HIPS[1], HIPS[0]]] - origin
    torso = torso.mean(axis=0) + (1.0 - TORSO_SHRINK) * (torso - torso.mean(axis=0))
    torso_mask = np.zeros(hsv.shape[:2], dtype=np.uint8)
    cv2.fillPoly(torso_mask, [np.round(torso).astype(np.int32)], 255)
    leg_mask = np.zeros_like(torso_mask)
    length_px = float(np.hypot(*(points[list(ANKLES)].mean(axis=0) - points[list(SHOULDERS)].mean(axis=0))))
    thickness = max(2, round(LEG_WIDTH_FRACTION * length_px))
    polylines = [np.round(points[list(leg)] - origin).astype(np.int32) for leg in legs]
    cv2.polylines(leg_mask, polylines, isClosed=False, color=255, thickness=thickness)
    leg_mask[torso_mask > 0] = 0
    for front in np.asarray(front_boxes_xyxy_px, dtype=np.float64).reshape(-1, 4):
        f_left, f_top = np.maximum(np.floor(front[:2] - origin).astype(int), 0)
        f_right, f_bottom = np.maximum(np.ceil(front[2:] - origin).astype(int), 0)
        torso_mask[f_top:f_bottom, f_left:f_right] = 0
        leg_mask[f_top:f_bottom, f_left:f_right] = 0
    histograms = []
    for mask in (torso_mask, leg_mask):
        if int(np.count_nonzero(mask)) < MIN_REGION_PIXELS:
            return None
        histogram = cv2.calcHist([hsv], [0, 1, 2], mask, list(APPEARANCE_BINS), _HSV_RANGES)
        histograms.append(histogram.reshape(-1))
    return encode_descriptor(np.array(histograms))
