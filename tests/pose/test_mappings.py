"""Coordinate maps between image pixels and the networks' inputs, checked on pixels (no model needed)."""

from __future__ import annotations

import numpy as np
import pytest

from service.pose.detector import MEAN_BGR, PAD_VALUE, STD_BGR, Letterbox, decode, letterbox
from service.pose.movenet import CropWindow, InputNormalisation, crop_window, extract_crop


def test_letterbox_places_image_top_left_and_maps_back() -> None:
    image = np.zeros((1080, 1920, 3), dtype=np.uint8)
    image[500:600, 1000:1200] = (255, 0, 0)  # a blue (BGR) block
    tensor, placement = letterbox(image, 640)
    assert tensor.shape == (1, 3, 640, 640) and tensor.dtype == np.float32
    assert placement.ratio == pytest.approx(640 / 1920)
    # BGR kept: the block is bright in channel 0 only; where it lands must map back to the block in the image.
    blue = tensor[0, 0] > (200 - MEAN_BGR[0]) / STD_BGR[0]
    rows, cols = np.nonzero(blue)
    box_input = np.array([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1], dtype=float)
    np.testing.assert_allclose(placement.to_image(box_input), [1000, 500, 1200, 600], atol=3.5)
    # Padding: rows below the resized 360-row image hold the normalised 114.
    np.testing.assert_allclose(tensor[0, :, 400, 10], (PAD_VALUE - MEAN_BGR) / STD_BGR, rtol=1e-6)
    np.testing.assert_allclose(tensor[0, :, 10, 10], (0 - MEAN_BGR) / STD_BGR, rtol=1e-6)


def test_stride_padded_letterbox_pads_only_to_the_stride() -> None:
    image = np.random.default_rng(3).integers(0, 256, (1080, 1920, 3), dtype=np.uint8)
    square, placement = letterbox(image, 640)
    tensor, same = letterbox(image, 640, square=False)
    assert tensor.shape == (1, 3, 384, 640) and placement == same
    np.testing.assert_array_equal(tensor, square[:, :, :384])  # the same pixels, fewer padding rows
    np.testing.assert_allclose(tensor[0, :, 370, 5], (PAD_VALUE - MEAN_BGR) / STD_BGR, rtol=1e-6)
    odd, _ = letterbox(image[:1000, :999], 640, square=False)
    assert odd.shape == (1, 3, 640, 640)  # 999 x 1000: the 639-px side rounds up to the stride


def test_letterbox_maps_are_inverse() -> None:
    placement = Letterbox(ratio=0.3125, size_px=640)
    points = np.random.default_rng(1).uniform(0, 2000, (50, 2))
    np.testing.assert_allclose(placement.to_image(placement.to_input(points)), points, rtol=1e-12)


def test_decode_thresholds_maps_clips_and_sorts() -> None:
    placement = Letterbox(ratio=0.5, size_px=640)
    dets = np.array(
        [
            [10, 10, 50, 100, 0.4],
            [400, 20, 700, 200, 0.9],  # right edge beyond the 1000-px-wide image once mapped: clipped
            [0, 0, 10, 10, 0.1],  # below threshold
            [600, 20, 700, 200, 0.8],  # entirely right of the image: clipped to nothing, dropped
        ],
        dtype=np.float32,
    )
    out = decode(dets, placement, (500, 1000), 0.3)
    np.testing.assert_allclose(out.scores, [0.9, 0.4], rtol=1e-6)
    np.testing.assert_allclose(out.boxes_xyxy_px, [[800, 40, 1000, 400], [20, 20, 100, 200]])


def test_crop_window_is_centred_square() -> None:
    window = crop_window((100.0, 200.0, 140.0, 300.0))
    assert window.side == 125  # 1.25 x the longer (100 px) side
    centre = (window.x0 + window.side / 2, window.y0 + window.side / 2)
    assert abs(centre[0] - 120.0) <= 0.5 and abs(centre[1] - 250.0) <= 0.5


def test_crop_maps_are_inverse() -> None:
    window = CropWindow(x0=-37, y0=812, side=413)
    points = np.random.default_rng(2).uniform(-100, 2000, (50, 2))
    np.testing.assert_allclose(window.to_image(window.to_normalised(points)), points, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("box", [(300.0, 400.0, 380.0, 600.0), (-20.0, 900.0, 90.0, 1080.0)])
def test_crop_content_lands_where_the_map_says(box: tuple[float, float, float, float]) -> None:
    """A marked pixel of the image appears in the crop at window.to_normalised(its position), outside is black."""
    image = np.full((1080, 1920, 3), 60, dtype=np.uint8)
    window = crop_window(box)
    target = np.array([window.x0 + 0.7 * window.side, window.y0 + 0.3 * window.side])
    x, y = (int(v) for v in target)
    image[y - 3 : y + 4, x - 3 : x + 4] = (0, 0, 255)  # red in BGR
    crop = extract_crop(image, window, 256)
    assert crop.shape == (256, 256, 3)
    red = (crop[..., 0] > 150) & (crop[..., 2] < 80)  # RGB now: red is channel 0
    rows, cols = np.nonzero(red)
    found = np.array([(cols.mean() + 0.5) / 256, (rows.mean() + 0.5) / 256])
    np.testing.assert_allclose(window.to_image(found), [x + 0.5, y + 0.5], atol=0.01 * window.side + 1)
    if window.x0 < 0:
        assert crop[:, :5].max() == 0  # beyond the left edge: black
    if window.y0 + window.side > 1080:
        assert crop[-5:].max() == 0


def test_input_normalisation_matches_the_graphs_arithmetic() -> None:
    """OpenCV's one-pass blob (uniform scale) and the numpy path give (x - offset) * scale - shift, NCHW, exactly."""
    crops = np.random.default_rng(4).integers(0, 256, (3, 8, 8, 3), dtype=np.uint8)
    ones = np.ones(3, dtype=np.float32)
    for offset, scale in ((0 * ones, ones / np.float32(127.5)), (np.float32([1, 2, 3]), np.float32([0.1, 0.2, 0.3]))):
        normalise = InputNormalisation(offset, scale, ones)
        expected = ((crops.astype(np.float32) - offset) * scale - ones).transpose(0, 3, 1, 2)
        tensor = normalise(crops)
        assert tensor.shape == (3, 3, 8, 8) and tensor.dtype == np.float32 and tensor.flags.c_contiguous
        np.testing.assert_array_equal(tensor, expected)
