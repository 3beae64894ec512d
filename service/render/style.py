"""Colours, line widths and labels that stay legible from a 640x480 thumbnail to a 1080p frame.

Every renderer sizes its strokes and fonts from one `Style`, derived from the image size, so that a label is
readable at both sizes without the caller picking numbers; text is always drawn on a dark box so it reads on
any background (bright pavement, dark clothes, the heat map's colours).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from service.domain import METRES_PER_FOOT

# BGR colours.
GREEN = (60, 200, 60)
RED = (40, 40, 235)
CYAN = (230, 210, 40)
PINK = (200, 120, 255)
LIGHT_RED = (110, 110, 255)
WHITE = (255, 255, 255)
DARK = (25, 25, 25)
GREY = (128, 128, 128)

FONT = cv2.FONT_HERSHEY_SIMPLEX
# Coordinates are passed to OpenCV in fixed point with this many fractional bits (sub-pixel accurate lines).
SHIFT = 4
_ONE = 1 << SHIFT
# Projected points are clamped to this many pixels around the image before drawing (OpenCV needs ints).
_CLAMP_PX = 1 << 14


@dataclass(frozen=True)
class Style:
    """Stroke widths and font size for an image of a given size."""

    line_px: int
    thin_px: int
    font_scale: float
    font_thickness: int
    pad_px: int
    marker_px: int

    @classmethod
    def for_size(cls, width_px: int, height_px: int) -> Style:
        """Scale with the shorter side: digits 12 px tall at 480 px, 27 px at 1080 px; strokes likewise."""
        s = max(min(width_px, height_px), 1) / 720.0
        return cls(
            line_px=max(1, round(2.5 * s)),
            thin_px=max(1, round(1.2 * s)),
            font_scale=max(0.42, 0.66 * s),
            font_thickness=max(1, round(1.6 * s)),
            pad_px=max(2, round(4 * s)),
            marker_px=max(3, round(7 * s)),
        )


def fixed(points: np.ndarray) -> np.ndarray:
    """Float pixel points -> OpenCV fixed-point int32 (see SHIFT), clamped to a sane range around the image."""
    p = np.clip(np.asarray(points, dtype=np.float64), -_CLAMP_PX, _CLAMP_PX)
    return np.round(p * _ONE).astype(np.int32)


def line(image: np.ndarray, p0: np.ndarray, p1: np.ndarray, color: tuple[int, ...] | float, thickness: int) -> None:
    """An anti-aliased line between float pixel points (in place)."""
    a, b = fixed(np.asarray(p0)), fixed(np.asarray(p1))
    cv2.line(image, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), color, thickness, cv2.LINE_AA, SHIFT)


def label(
    image: np.ndarray,
    text: str,
    anchor: tuple[float, float],
    style: Style,
    *,
    color: tuple[int, int, int] = WHITE,
    background: tuple[int, int, int] = DARK,
    align: str = "center",
) -> tuple[int, int, int, int]:
    """Text on a dark box (in place), kept inside the image; returns the box (x0, y0, x1, y1).

    `anchor` is the box centre for align="center", else the box corner named by align: "topleft",
    "bottomleft", "topright" or "bottomright".
    """
    (_, th), _ = cv2.getTextSize(text, FONT, style.font_scale, style.font_thickness)
    bw, bh = label_size(text, style)
    ax, ay = anchor
    if align == "center":
        x0, y0 = ax - bw / 2, ay - bh / 2
    else:
        x0 = ax - bw if align.endswith("right") else ax
        y0 = ay if align.startswith("top") else ay - bh
    height, width = image.shape[:2]
    x0 = int(np.rint(min(max(x0, 0), max(width - bw, 0))))
    y0 = int(np.rint(min(max(y0, 0), max(height - bh, 0))))
    cv2.rectangle(image, (x0, y0), (x0 + bw - 1, y0 + bh - 1), background, -1)
    origin = (x0 + style.pad_px, y0 + style.pad_px + th)
    cv2.putText(image, text, origin, FONT, style.font_scale, color, style.font_thickness, cv2.LINE_AA)
    return x0, y0, x0 + bw - 1, y0 + bh - 1


def label_size(text: str, style: Style) -> tuple[int, int]:
    """(width, height) in pixels of the box `label` draws for `text`."""
    (tw, th), baseline = cv2.getTextSize(text, FONT, style.font_scale, style.font_thickness)
    return tw + 2 * style.pad_px, th + baseline + 2 * style.pad_px


def text_height(style: Style) -> int:
    """Height in pixels of a one-line label box drawn with `style`."""
    (_, th), baseline = cv2.getTextSize("0", FONT, style.font_scale, style.font_thickness)
    return th + baseline + 2 * style.pad_px


def format_distance(distance_m: float, unit: str = "m") -> str:
    """'1.42 m' or '4.7 ft': the label on a link or a pair."""
    if unit == "ft":
        return f"{distance_m / METRES_PER_FOOT:.1f} ft"
    return f"{distance_m:.2f} m"
