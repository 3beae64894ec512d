"""Posted pictures: what they are, how big they claim to be, and whether they decode, before anything keeps them.

The API must answer a bad image with a 4xx at once rather than let a pose worker discover it later, and must
not be the victim of a decompression bomb (a small file that decodes to gigapixels). So the dimensions are read
from the header (PNG's IHDR, JPEG's SOF marker) and checked against a pixel budget *before* decoding; only then
is the image decoded in full, which also catches truncated and corrupt files. Pure functions over bytes.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

JPEG = "image/jpeg"
PNG = "image/png"
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers that carry the image size (baseline, progressive, lossless, arithmetic...).
_SOF_MARKERS = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF})
# Markers without a length field.
_STANDALONE_MARKERS = frozenset({0x01, *range(0xD0, 0xD8)})


class ImageError(ValueError):
    """The bytes are not a usable JPEG or PNG; the message says why, for the client."""


@dataclass(frozen=True)
class ImageHeader:
    content_type: str
    width_px: int
    height_px: int

    @property
    def pixels(self) -> int:
        return self.width_px * self.height_px


def sniff_content_type(data: bytes) -> str | None:
    """The image type from the file's magic bytes (clients mislabel uploads; the bytes decide)."""
    if data.startswith(_PNG_SIGNATURE):
        return PNG
    if data.startswith(b"\xff\xd8\xff"):
        return JPEG
    return None


_OTHER_FORMATS = (
    ("HEIC", lambda data: data[4:8] == b"ftyp" and data[8:12] in (b"heic", b"heix", b"hevc", b"mif1", b"msf1")),
    ("AVIF", lambda data: data[4:8] == b"ftyp" and data[8:12] in (b"avif", b"avis")),
    ("WebP", lambda data: data[:4] == b"RIFF" and data[8:12] == b"WEBP"),
    ("GIF", lambda data: data[:6] in (b"GIF87a", b"GIF89a")),
    ("TIFF", lambda data: data[:4] in (b"II*\x00", b"MM\x00*")),
    ("BMP", lambda data: data[:2] == b"BM"),
)


def other_image_format(data: bytes) -> str | None:
    """The name of a picture format posemetry does not read, when the bytes are one: an iPhone saves HEIC unless
    told otherwise, and the client deserves to hear what it sent rather than 'unrecognised'."""
    return next((name for name, matches in _OTHER_FORMATS if matches(data)), None)


def read_header(data: bytes) -> ImageHeader:
    """Type and size from the header alone; raises ImageError for anything else or a header cut short."""
    if not data:
        raise ImageError("the image is empty")
    content_type = sniff_content_type(data)
    if content_type == PNG:
        width, height = _png_size(data)
    elif content_type == JPEG:
        width, height = _jpeg_size(data)
    else:
        raise ImageError("not a JPEG or PNG image (unrecognised file signature)")
    if width <= 0 or height <= 0:
        raise ImageError(f"the image header gives an empty size {width}x{height}")
    return ImageHeader(content_type, width, height)


def _png_size(data: bytes) -> tuple[int, int]:
    # Signature (8), IHDR chunk length (4) and type (4), then width and height as big-endian uint32.
    if len(data) < 24 or data[12:16] != b"IHDR":
        raise ImageError("PNG without a complete IHDR header")
    width, height = struct.unpack(">II", data[16:24])
    return int(width), int(height)


def _jpeg_size(data: bytes) -> tuple[int, int]:
    offset = 2
    while offset + 4 <= len(data):
        if data[offset] != 0xFF:
            raise ImageError("corrupt JPEG: marker expected")
        marker = data[offset + 1]
        if marker == 0xFF:  # fill byte
            offset += 1
            continue
        if marker in _STANDALONE_MARKERS:
            offset += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image, or scan data before any frame header
            break
        (length,) = struct.unpack(">H", data[offset + 2 : offset + 4])
        if marker in _SOF_MARKERS:
            if offset + 9 > len(data):
                break
            height, width = struct.unpack(">HH", data[offset + 5 : offset + 9])
            return int(width), int(height)
        offset += 2 + length
    raise ImageError("JPEG without a frame header (SOF marker): truncated or not an image")


def _complete(data: bytes, content_type: str) -> bool:
    """Whether the file has its end marker: decoders fill a truncated image with grey instead of failing."""
    return (_jpeg_end(data) if content_type == JPEG else _png_end(data)) is not None


def _png_end(data: bytes) -> int | None:
    """Where the PNG's IEND chunk ends, walking its chunks by their lengths; None when the file stops before it."""
    offset = len(_PNG_SIGNATURE)
    while offset + 12 <= len(data):  # length, type and CRC: 12 bytes around a chunk's data
        (length,) = struct.unpack(">I", data[offset : offset + 4])
        kind, offset = data[offset + 4 : offset + 8], offset + 12 + length
        if kind == b"IEND":
            return offset if offset <= len(data) else None
    return None


def _jpeg_end(data: bytes) -> int | None:
    """Where the JPEG's end-of-image marker ends, or None when the file stops (or breaks) before it.

    Walked, not looked for at the end of the file: phones append to their JPEGs (a Pixel's or Samsung's motion
    photo is the JPEG and then a video), and those bytes are not the picture. Segments are skipped by their
    lengths, and a scan's entropy-coded data up to the next marker, since there 0xFF is always followed by 0x00
    or a restart marker.
    """
    offset, end = 2, len(data)
    while offset + 2 <= end:
        if data[offset] != 0xFF:
            return None
        marker = data[offset + 1]
        if marker == 0xD9:
            return offset + 2
        if marker == 0xFF or marker in _STANDALONE_MARKERS:  # a fill byte, or a marker without a length
            offset += 1 if marker == 0xFF else 2
            continue
        if offset + 4 > end:
            return None
        offset += 2 + struct.unpack(">H", data[offset + 2 : offset + 4])[0]
        if marker != 0xDA:
            continue
        while True:  # the scan's data: to the next 0xFF that starts a marker other than a restart
            offset = data.find(b"\xff", offset)
            if offset < 0 or offset + 1 >= end:
                return None
            following = data[offset + 1]
            if following == 0x00 or 0xD0 <= following <= 0xD7:
                offset += 2
            elif following == 0xFF:
                offset += 1
            else:
                break
    return None


def decode(data: bytes, *, max_pixels: int) -> tuple[ImageHeader, np.ndarray]:
    """The header and the decoded (H, W, 3) uint8 BGR image, or ImageError; refuses more than max_pixels.

    Raises ImageTooLargeError (an ImageError) for the pixel budget, so callers can answer 413 rather than 422.
    The picture is the one a viewer shows: OpenCV turns a JPEG by its EXIF orientation (a phone held upright, a
    camera mounted on its side writes the sensor's rows and says how to turn them), and the header returned gives
    that picture's size, which is the one the camera, the keypoints and the overlays are in.
    """
    import cv2

    header = read_header(data)
    if header.pixels > max_pixels:
        raise ImageTooLargeError(
            f"the image is {header.width_px}x{header.height_px} = {header.pixels} pixels; at most {max_pixels} "
            "are accepted (setting max_image_pixels)"
        )
    if not _complete(data, header.content_type):
        raise ImageError(f"truncated {header.content_type.split('/')[1].upper()}: the end-of-image marker is missing")
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise ImageError(f"the {header.content_type} could not be decoded (corrupt image data)")
    shown = ImageHeader(header.content_type, width_px=image.shape[1], height_px=image.shape[0])
    if (shown.height_px, shown.width_px) not in (
        (header.height_px, header.width_px),
        (header.width_px, header.height_px),
    ):
        raise ImageError(
            f"the image decodes to {shown.width_px}x{shown.height_px}, not the {header.width_px}x{header.height_px} "
            "its header declares"
        )
    return shown, image


class ImageTooLargeError(ImageError):
    """More pixels than the budget allows (a decompression bomb, or simply too big)."""
