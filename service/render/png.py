"""PNG bytes of a rendered picture, the one format the API serves pictures in (lossless, so colours are exact)."""

from __future__ import annotations

import cv2
import numpy as np


def encode_png(image: np.ndarray, *, compression: int = 3) -> bytes:
    """PNG bytes of an (H, W) grey, (H, W, 3) BGR or (H, W, 4) BGRA uint8 image.

    Compression 3 (of 0-9) is about as small as 9 for drawings at a fraction of the time.
    """
    array = np.asarray(image)
    if array.dtype != np.uint8:
        raise ValueError(f"PNG encoding needs uint8 pixels, got {array.dtype}")
    if array.ndim not in (2, 3) or (array.ndim == 3 and array.shape[2] not in (1, 3, 4)) or array.size == 0:
        raise ValueError(f"not an image shape: {array.shape}")
    ok, buffer = cv2.imencode(".png", np.ascontiguousarray(array), [cv2.IMWRITE_PNG_COMPRESSION, compression])
    if not ok:
        raise ValueError("OpenCV could not encode the image as PNG")
    return buffer.tobytes()
