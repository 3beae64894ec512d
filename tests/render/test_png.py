"""PNG bytes decode back to the very same pixels."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from service.render.png import encode_png


@pytest.mark.parametrize("shape", [(1, 1, 3), (480, 640, 3), (7, 5), (33, 17, 4)])
def test_png_round_trip(shape):
    image = np.random.default_rng(0).integers(0, 256, shape, dtype=np.uint8)
    data = encode_png(image)
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(back, image)


@pytest.mark.parametrize(
    "bad", [np.zeros((4, 4), np.float32), np.zeros((0, 4, 3), np.uint8), np.zeros((4, 4, 2), np.uint8)]
)
def test_png_refuses_what_is_not_an_image(bad):
    with pytest.raises(ValueError):
        encode_png(bad)
