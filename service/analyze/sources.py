"""Where the frames come from: a video file (OpenCV/FFmpeg) or a folder of images, read with a stride.

A source is read twice: once for pose, once to draw the overlays after the calibration exists (holding every
decoded 1080p frame in memory would take gigabytes on a long video). So a source is a description that opens
the file anew on each `frames()` call and yields the same frames, in the same order, each time.

Frames are numbered as in the source: a video's frame number (0-based), a folder's position in name order
("natural" order, so frame_2 comes before frame_10). A frame that cannot be used (an unreadable or truncated
image, one of another size than the first) is yielded as a `SkippedFrame` with the reason rather than ending the
run: one bad file in a folder of thousands should cost that file, not the analysis.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from service.frames.images import ImageError, decode

from .errors import AnalyzeError

# Decoded through service.frames.images (header check, pixel budget, truncation) ...
CHECKED_SUFFIXES = frozenset({".jpg", ".jpeg", ".png"})
# ... or by OpenCV alone.
OTHER_IMAGE_SUFFIXES = frozenset({".bmp", ".tif", ".tiff", ".webp"})
IMAGE_SUFFIXES = CHECKED_SUFFIXES | OTHER_IMAGE_SUFFIXES
# An image folder's overlay video is written at this many frames per second (its own rate, `--fps`, may be one
# image every few seconds: a slide show, not a video).
IMAGE_FOLDER_VIDEO_FPS = 5.0
# Most pixels a folder image may decode to (a 1e8-pixel frame would take ~300 MB as BGR and pose nothing better).
MAX_IMAGE_PIXELS = 100_000_000

SourceKind = Literal["video", "images"]


@dataclass(frozen=True)
class SourceFrame:
    """One decoded frame."""

    index: int
    """Frame number in the source (video frame, or position of the file in name order)."""
    time_s: float | None
    """Seconds from the start of a video (index / fps); None for images."""
    file: str | None
    """The image's file name; None for a video."""
    image: np.ndarray
    """(H, W, 3) uint8 BGR."""


@dataclass(frozen=True)
class SkippedFrame:
    """A frame the source could not deliver, and why."""

    index: int
    file: str | None
    reason: str


def _natural_key(path: Path) -> list[int | str]:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path.name)]


@dataclass(frozen=True)
class VideoSource:
    """A video file; every `stride`-th frame from the first, at most `max_frames` of them."""

    path: Path
    stride: int
    max_frames: int | None
    image_size_px: tuple[int, int]
    fps: float | None
    frame_count: int | None
    """What the container declares (may be approximate; only used for the progress bar)."""
    kind: SourceKind = "video"

    @classmethod
    def open(cls, path: Path, stride: int = 1, max_frames: int | None = None) -> VideoSource:
        capture = cv2.VideoCapture(str(path))
        try:
            if not capture.isOpened():
                raise AnalyzeError(f"cannot read {path} as a video (not a video file, or a codec OpenCV lacks)")
            ok, first = capture.read()
            if not ok or first is None:
                raise AnalyzeError(f"{path} opens as a video but no frame decodes (empty or corrupt)")
            fps = float(capture.get(cv2.CAP_PROP_FPS))
            count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        finally:
            capture.release()
        return cls(
            path=path,
            stride=stride,
            max_frames=max_frames,
            image_size_px=(int(first.shape[1]), int(first.shape[0])),
            fps=fps if math.isfinite(fps) and fps > 0 else None,
            frame_count=count if count > 0 else None,
        )

    def planned(self) -> int | None:
        """How many frames `frames()` should yield, when the container says how long it is."""
        if self.frame_count is None:
            return self.max_frames
        planned = -(-self.frame_count // self.stride)
        return planned if self.max_frames is None else min(planned, self.max_frames)

    def frames(self) -> Iterator[SourceFrame | SkippedFrame]:
        capture = cv2.VideoCapture(str(self.path))
        try:
            index = yielded = 0
            while self.max_frames is None or yielded < self.max_frames:
                if index % self.stride:
                    if not capture.grab():  # skipped frames are demuxed and decoded, not converted to BGR
                        return
                    index += 1
                    continue
                ok, image = capture.read()
                if not ok or image is None:
                    return
                time_s = index / self.fps if self.fps else None
                if (image.shape[1], image.shape[0]) != self.image_size_px:
                    reason = f"frame size {image.shape[1]}x{image.shape[0]} differs from the first frame's"
                    yield SkippedFrame(index, None, reason)
                else:
                    yield SourceFrame(index, time_s, None, image)
                yielded += 1
                index += 1
        finally:
            capture.release()


@dataclass(frozen=True)
class ImageSource:
    """Image files (a folder's, in natural name order, or a single one); every `stride`-th, at most `max_frames`."""

    path: Path
    files: tuple[Path, ...]
    """The files that will be read (stride and max_frames already applied)."""
    stride: int
    max_frames: int | None
    image_size_px: tuple[int, int]
    """The size of the first readable image; others of another size are skipped."""
    fps: float | None = None
    """Images per second the camera took (the user's `--fps`): the images' times, for linking one person's
    sightings into one individual and for static spots; None: unknown, so neither."""
    kind: SourceKind = "images"

    @classmethod
    def open(cls, path: Path, stride: int = 1, max_frames: int | None = None, fps: float | None = None) -> ImageSource:
        if path.is_dir():
            found = sorted(
                (p for p in path.iterdir() if p.is_file() and not p.name.startswith(".") and _is_image(p)),
                key=_natural_key,
            )
            if not found:
                raise AnalyzeError(f"no images in {path} (looked for {', '.join(sorted(IMAGE_SUFFIXES))})")
        else:
            found = [path]
        files = tuple(found[::stride][:max_frames])
        for file in files:
            try:
                image = _read_image(file)
            except ImageError:
                continue
            return cls(path, files, stride, max_frames, (int(image.shape[1]), int(image.shape[0])), fps)
        raise AnalyzeError(f"none of the {len(files)} images in {path} could be read")

    def planned(self) -> int | None:
        return len(self.files)

    def frames(self) -> Iterator[SourceFrame | SkippedFrame]:
        for position, file in enumerate(self.files):
            index = position * self.stride
            try:
                image = _read_image(file)
            except ImageError as exc:
                yield SkippedFrame(index, file.name, str(exc))
                continue
            if (image.shape[1], image.shape[0]) != self.image_size_px:
                width, height = self.image_size_px
                reason = f"image size {image.shape[1]}x{image.shape[0]} differs from the first image's {width}x{height}"
                yield SkippedFrame(index, file.name, reason)
                continue
            yield SourceFrame(index, index / self.fps if self.fps else None, file.name, image)


FrameSource = VideoSource | ImageSource


def _is_image(path: Path) -> bool:
    return path.suffix.lower() in IMAGE_SUFFIXES


def _read_image(path: Path) -> np.ndarray:
    """A BGR image, or ImageError saying why not."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ImageError(f"cannot read the file: {exc.strerror or exc}") from None
    if path.suffix.lower() in CHECKED_SUFFIXES:
        return decode(data, max_pixels=MAX_IMAGE_PIXELS)[1]
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ImageError("not a readable image")
    return image


def open_source(path: Path, *, stride: int = 1, max_frames: int | None = None, fps: float | None = None) -> FrameSource:
    """The frames at `path`: a folder of images, one image, or a video; AnalyzeError when there are none.

    `fps`: the rate an image folder was taken at (a video's own is read from the file)."""
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise AnalyzeError(f"the frame rate must be a positive number of images per second, got {fps:g}")
    if stride < 1:
        raise AnalyzeError(f"the stride must be at least 1, got {stride}")
    if max_frames is not None and max_frames < 1:
        raise AnalyzeError(f"max frames must be at least 1, got {max_frames}")
    if not path.exists():
        raise AnalyzeError(f"{path} does not exist")
    if path.is_dir() or _is_image(path):
        return ImageSource.open(path, stride, max_frames, fps)
    if not path.is_file():
        raise AnalyzeError(f"{path} is neither a video file nor a folder of images")
    if fps is not None:
        raise AnalyzeError("--fps is for a folder of images: a video's frame times come from the video")
    return VideoSource.open(path, stride, max_frames)
