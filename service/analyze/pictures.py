"""The pictures of a run: each frame's overlay and top-down map (images), and the same as videos.

Drawn by the service's renderers (service.render) from the same results the tables hold, so a picture can never
disagree with the numbers. The top-down maps of one run share one view, fitted to where people stood over the
whole run, so successive maps (and the frames of topdown.mp4) line up instead of jumping with each frame's crowd.
Frames are decoded again from the source for this (holding a whole video in memory until the calibration exists
would take gigabytes) and drawn as they are measured.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from service.frames.schemas import FrameResult
from service.render.frame import FramePictures
from service.render.ground import GroundFrame
from service.render.png import encode_png
from service.render.style import Style, label
from service.render.topdown import TopDownView, fit_view

from .analysis import Analysis, AnalyzedFrame, Observer
from .sources import IMAGE_FOLDER_VIDEO_FPS
from .writers import OVERLAY_DIR, OVERLAY_VIDEO, TOPDOWN_DIR, TOPDOWN_VIDEO

TOPDOWN_SIZE_PX = 800
JPEG_QUALITY = 92
# zlib level 1: a 1080p overlay in ~90 ms instead of ~125 ms at level 3, for 10 % more bytes (a long video
# writes thousands of them).
PNG_COMPRESSION = 1
VIDEO_FOURCC = "mp4v"
# The shared top-down view covers these percentiles of the usable people's ground positions (and the camera's
# foot), so one person placed absurdly far (a misdetection near the horizon) does not shrink every map.
_VIEW_PERCENTILES = (2.0, 98.0)


def topdown_view(analysis: Analysis, size_px: int = TOPDOWN_SIZE_PX) -> TopDownView:
    """One view for every map of the run: where the usable people stood (the bulk of them), and the camera's foot.

    Fitted before any frame is measured (the frames are drawn as they are measured), from the evidence's ankle
    centres on the ground.
    """
    calibration = analysis.calibration
    ground = np.zeros((0, 2))
    if calibration is not None and len(analysis.evidence):
        ground = GroundFrame.from_calibration(calibration).pixels_to_ground(analysis.evidence.bottoms_px)
        ground = ground[np.all(np.isfinite(ground), axis=1)]
    if len(ground):
        lo, hi = np.percentile(ground, _VIEW_PERCENTILES, axis=0)
        ground = np.array([lo, hi])
    return fit_view(np.vstack([ground, np.zeros((1, 2))]), size_px)


def picture_stem(frame: AnalyzedFrame) -> str:
    """A frame's pictures are named after its image file (folders), else `frame_NNNNNN` by frame number."""
    return Path(frame.file).stem if frame.file is not None else f"frame_{frame.index:06d}"


def _caption(frame: AnalyzedFrame, result: FrameResult) -> str:
    parts = [frame.file if frame.file is not None else f"frame {frame.index}"]
    if frame.time_s is not None:
        parts.append(f"{frame.time_s:.2f} s")
    count = len(result.violations)
    parts.append(f"{count} violation{'s' * (count != 1)}")
    return "   ".join(parts)


def _encode(image: np.ndarray, image_format: str) -> bytes:
    if image_format == "png":
        return encode_png(image, compression=PNG_COMPRESSION)
    ok, buffer = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError("OpenCV could not encode the image as JPEG")
    return buffer.tobytes()


class _Video:
    """An mp4 written frame by frame; a writer OpenCV cannot open is reported once and skipped."""

    def __init__(self, path: Path, fps: float, size_px: tuple[int, int], observer: Observer) -> None:
        self.path = path
        self.writer: cv2.VideoWriter | None = cv2.VideoWriter(
            str(path), cv2.VideoWriter_fourcc(*VIDEO_FOURCC), fps, size_px
        )
        if not self.writer.isOpened():
            observer.note(f"cannot write {path} (no {VIDEO_FOURCC} encoder in this OpenCV); skipping the video")
            self.writer = None

    def write(self, image: np.ndarray) -> None:
        if self.writer is not None:
            self.writer.write(image)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.release()


class PictureWriter:
    """Each measured frame's overlay and map, as images and into the videos (a context manager: videos are closed
    on exit). Disabled, it draws nothing."""

    def __init__(self, analysis: Analysis, out_dir: Path, observer: Observer, *, enabled: bool = True) -> None:
        self.analysis = analysis
        self.out_dir = out_dir
        options = analysis.options
        self.images = enabled and options.write_images
        self.view = topdown_view(analysis) if enabled else None
        if self.images:
            (out_dir / OVERLAY_DIR).mkdir(exist_ok=True)
            (out_dir / TOPDOWN_DIR).mkdir(exist_ok=True)
        self.videos: list[_Video] = []
        if enabled and analysis.wants_video and self.view is not None:
            source = analysis.source
            fps = source.fps / source.stride if source.kind == "video" and source.fps else IMAGE_FOLDER_VIDEO_FPS
            self.videos = [
                _Video(out_dir / OVERLAY_VIDEO, fps, source.image_size_px, observer),
                _Video(out_dir / TOPDOWN_VIDEO, fps, (self.view.width_px, self.view.height_px), observer),
            ]

    def __enter__(self) -> PictureWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        for video in self.videos:
            video.close()

    def draw(self, image: np.ndarray, frame: AnalyzedFrame, result: FrameResult) -> None:
        if self.view is None:
            return
        options = self.analysis.options
        pictures = FramePictures.of(result, frame.people, self.analysis.calibration, options.unit)
        caption = _caption(frame, result)
        overlay, topdown = pictures.overlay(image), pictures.topdown(view=self.view, title=caption)
        height, width = overlay.shape[:2]
        label(overlay, caption, (0, 0), Style.for_size(width, height), align="topleft")
        if self.images:
            name = f"{picture_stem(frame)}.{options.image_format}"
            (self.out_dir / OVERLAY_DIR / name).write_bytes(_encode(overlay, options.image_format))
            (self.out_dir / TOPDOWN_DIR / name).write_bytes(_encode(topdown, options.image_format))
        if self.videos:
            self.videos[0].write(overlay)
            self.videos[1].write(topdown)
