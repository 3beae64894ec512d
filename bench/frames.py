"""Simulated keypoint frames for the speed benchmarks, encoded once before a run so that posting costs no JSON work.

Two kinds of camera, both from bench.simulate (surveillance preset: the truth is a real pinhole camera
over a ground plane, with pixel noise and a spread of heights):

- `simulated_frames`: every frame a fresh draw of people (the ingest benchmark: only the cost of a frame matters).
- `walking_frames`: the same people walking across the camera's ground from frame to frame, at walking speed,
  turning back at the edge of the view. The load benchmark uses these: distances, violations and webhook
  cooldowns then behave as on a real street (a close pair stays close for a while), not as noise.

People are encoded as COCO-17 keypoints (what every pose model emits; the service reads the shoulder and ankle
centres) or as explicit centres, with pixel coordinates rounded to 0.01 px and scores to 0.001, as a sensible
client would send them.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace

import numpy as np

from bench.simulate import Scene, SceneConfig, draw_scene, project

PEOPLE_PER_FRAME = 20
PAYLOADS = ("coco17", "centres")
WALKING_SPEED_M_S = (0.8, 1.6)
# Chance per frame that a walker picks a new direction (people wander, they do not walk on rails).
TURN_PROBABILITY = 0.02

# Where each COCO-17 keypoint sits along the ankle-centre (0) to shoulder-centre (1) segment: head above the
# shoulders, hips and knees between, elbows and wrists beside. Shoulders (5, 6) and ankles (15, 16) are exact
# left/right pairs around the centres, so the centres the service computes are the simulated ones.
_ALONG = np.array([1.25, 1.3, 1.3, 1.27, 1.27, 1.0, 1.0, 0.8, 0.8, 0.6, 0.6, 0.5, 0.5, 0.25, 0.25, 0.0, 0.0])
_SIDE = np.where(np.arange(17) % 2 == 1, -1.0, 1.0)


def coco17_keypoints(tops_px: np.ndarray, bottoms_px: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(n, 17, 3) COCO-17 keypoints [x, y, score] whose shoulder and ankle centres are `tops_px`, `bottoms_px`."""
    axis = tops_px - bottoms_px
    half_width = np.maximum(0.12 * np.hypot(axis[:, 0], axis[:, 1]), 2.0)
    points = bottoms_px[:, None, :] + axis[:, None, :] * _ALONG[None, :, None]
    points[:, :, 0] += _SIDE[None, :] * half_width[:, None]
    scores = rng.uniform(0.6, 0.99, (len(tops_px), 17, 1))
    return np.concatenate((points, scores), axis=2)


def people_json(tops_px: np.ndarray, bottoms_px: np.ndarray, payload: str, rng: np.random.Generator) -> bytes:
    """One frame's `people` array, encoded."""
    if payload == "coco17":
        keypoints = coco17_keypoints(tops_px, bottoms_px, rng)
        keypoints[:, :, :2] = np.round(keypoints[:, :, :2], 2)
        keypoints[:, :, 2] = np.round(keypoints[:, :, 2], 3)
        people: list[dict[str, object]] = [{"keypoints": person} for person in keypoints.tolist()]
    elif payload == "centres":
        tops, bottoms = np.round(tops_px, 2).tolist(), np.round(bottoms_px, 2).tolist()
        people = [{"shoulder": top, "ankle": bottom} for top, bottom in zip(tops, bottoms, strict=True)]
    else:
        raise ValueError(f"unknown payload {payload!r}; choose from {', '.join(PAYLOADS)}")
    return json.dumps(people, separators=(",", ":")).encode()


def camera_body(config: SceneConfig) -> dict[str, object]:
    """The PUT body of a camera that sees `config`'s scenes."""
    width, height = config.image_size
    return {"image_width_px": width, "image_height_px": height, "person_height_m": config.height_mean_m}


def simulated_frames(
    camera_count: int, frames_per_camera: int, payload: str, seed: int
) -> tuple[dict[str, object], list[list[bytes]]]:
    """One camera configuration (PUT body) and, per camera, frame bodies with an empty timestamp to fill in."""
    rng = np.random.default_rng(seed)
    config = SceneConfig.surveillance(n_people=PEOPLE_PER_FRAME * frames_per_camera)
    bodies: list[list[bytes]] = []
    for _ in range(camera_count):
        scene = draw_scene(config, rng)
        frames = []
        for index in range(frames_per_camera):
            people = slice(index * PEOPLE_PER_FRAME, (index + 1) * PEOPLE_PER_FRAME)
            encoded = people_json(scene.tops_px[people], scene.bottoms_px[people], payload, rng)
            frames.append(b'{"timestamp": "", "people": ' + encoded + b"}")
        bodies.append(frames)
    return camera_body(config), bodies


# --------------------------------------------------------------------------------------------------- walking


@dataclass(frozen=True)
class WalkingCamera:
    """One simulated camera's truth and its frames' `people` arrays, encoded, in time order."""

    scene: Scene
    people: list[bytes]

    def frame(self, index: int) -> bytes:
        """Frame `index` of an endless walk: the recorded frames forwards, then backwards, and so on, so people
        never jump when the recording wraps around."""
        period = max(2 * len(self.people) - 2, 1)
        position = index % period
        return self.people[position if position < len(self.people) else period - position]


def _ground_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two orthonormal directions on the ground: across the view, and away from the camera."""
    forward = np.array([0.0, 0.0, 1.0]) - normal[2] * normal
    forward /= np.linalg.norm(forward)
    return np.cross(normal, forward), forward


def _visible(scene: Scene, bottoms_m: np.ndarray, heights_m: np.ndarray) -> np.ndarray:
    """Which people have both their ankle and shoulder centres inside the image, in front of the camera."""
    width, height = scene.image_size
    tops_m = bottoms_m + heights_m[:, None] * scene.normal
    ok = (bottoms_m[:, 2] > 0.3) & (tops_m[:, 2] > 0.3)
    for points in (bottoms_m, tops_m):
        px = project(points, scene.fx, scene.fy, scene.cx, scene.cy)
        ok &= (px[:, 0] >= 0) & (px[:, 0] <= width) & (px[:, 1] >= 0) & (px[:, 1] <= height)
    return ok


def walking_frames(
    config: SceneConfig, rng: np.random.Generator, *, frames: int, fps: float, payload: str
) -> WalkingCamera:
    """`frames` frames at `fps` of `config.n_people` people walking in one camera's view (see the module doc)."""
    scene = draw_scene(config, rng)
    side, forward = _ground_axes(scene.normal)
    n = config.n_people
    bottoms_m = scene.points_bottom.copy()
    heights_m = scene.heights
    headings = rng.uniform(0.0, 2 * np.pi, n)
    speeds = rng.uniform(*WALKING_SPEED_M_S, n)
    people = []
    for _ in range(frames):
        tops_m = bottoms_m + heights_m[:, None] * scene.normal
        tops_px = project(tops_m, scene.fx, scene.fy, scene.cx, scene.cy) + rng.normal(0, config.noise_px, (n, 2))
        bottoms_px = project(bottoms_m, scene.fx, scene.fy, scene.cx, scene.cy) + rng.normal(0, config.noise_px, (n, 2))
        people.append(people_json(tops_px, bottoms_px, payload, rng))
        turning = rng.random(n) < TURN_PROBABILITY
        headings[turning] = rng.uniform(0.0, 2 * np.pi, int(turning.sum()))
        step = (speeds / fps)[:, None] * (np.cos(headings)[:, None] * side + np.sin(headings)[:, None] * forward)
        moved = bottoms_m + step
        stays = _visible(scene, moved, heights_m)
        bottoms_m = np.where(stays[:, None], moved, bottoms_m)
        # Walkers about to leave the view turn around (with a little spread) instead.
        headings[~stays] += np.pi + rng.uniform(-0.5, 0.5, int((~stays).sum()))
    return WalkingCamera(scene, people)


def walking_cameras(
    count: int, seed: int, *, frames: int, fps: float, payload: str = "coco17", people: int = PEOPLE_PER_FRAME
) -> tuple[dict[str, object], list[WalkingCamera]]:
    """`count` cameras, each its own scene (its own height, tilt and field of view), and their PUT body."""
    rng = np.random.default_rng(seed)
    config = replace(SceneConfig.surveillance(), n_people=people)
    walks = [walking_frames(config, rng, frames=frames, fps=fps, payload=payload) for _ in range(count)]
    return camera_body(config), walks
