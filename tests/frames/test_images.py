"""Image frames over HTTP: accepted as raw JPEG/PNG bodies or multipart forms, refused with a clear 4xx otherwise."""

from __future__ import annotations

import struct
import uuid
import zlib

import cv2
import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from hypothesis import given, settings
from hypothesis import strategies as st

from service.frames.images import ImageError, decode
from service.frames.repository import frame_image
from tests.support.app import HEIGHT_PX, WIDTH_PX, assert_problem, encoded, with_exif_orientation
from tests.support.dispatch import RecordingDispatcher


@pytest.fixture(scope="module")
def jpeg() -> bytes:
    return encoded(".jpg")


@pytest.fixture(scope="module")
def png() -> bytes:
    return encoded(".png")


def png_header_only(width: int, height: int) -> bytes:
    """A PNG that claims a huge size in its header: what a decompression bomb looks like before decoding."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    return b"\x89PNG\r\n\x1a\n" + chunk + b"\x00" * 64


def test_raw_jpeg_is_stored_detecting_and_dispatched(
    client: TestClient, camera: str, jpeg: bytes, dispatcher: RecordingDispatcher, app: FastAPI
) -> None:
    response = client.post(
        f"/v1/cameras/{camera}/frames?timestamp=2026-01-01T12:00:00Z&frame_id=img-1",
        content=jpeg,
        headers={"Content-Type": "image/jpeg"},
    )
    assert response.status_code == 202, response.text
    body = response.json()
    assert (body["status"], body["people"], body["created"], body["client_frame_id"]) == ("detecting", 0, True, "img-1")
    frame_id = uuid.UUID(body["frame_id"])
    assert dispatcher.images == [(camera, frame_id)] and dispatcher.frames == []
    frame = client.get(body["url"]).json()
    assert (frame["source"], frame["status"], frame["image_kept"], frame["detections"]) == (
        "image",
        "detecting",
        True,
        None,
    )
    assert frame["timestamp"].startswith("2026-01-01T12:00:00")
    with app.state.session_factory() as session:
        image = frame_image(session, frame_id)
        assert image is not None and image.data == jpeg and image.content_type == "image/jpeg"
        assert (image.width_px, image.height_px) == (WIDTH_PX, HEIGHT_PX)
    retry = client.post(
        f"/v1/cameras/{camera}/frames?frame_id=img-1", content=jpeg, headers={"Content-Type": "image/jpeg"}
    )
    assert retry.status_code == 200 and retry.json()["frame_id"] == body["frame_id"]


def test_multipart_png_with_form_fields(client: TestClient, camera: str, png: bytes) -> None:
    response = client.post(
        f"/v1/cameras/{camera}/frames",
        files={"image": ("frame.png", png, "image/png")},
        data={"timestamp": "2026-03-04T05:06:07+01:00", "frame_id": "form-1"},
    )
    assert response.status_code == 202, response.text
    frame = client.get(response.json()["url"]).json()
    assert frame["client_frame_id"] == "form-1"
    assert frame["timestamp"].startswith("2026-03-04T04:06:07")


@pytest.mark.parametrize(
    ("mutate", "status", "fragment"),
    [
        (lambda data: data[: len(data) // 2], 422, "truncated"),
        (lambda data: data[:40], 422, "truncated"),
        (lambda data: data[:3] + b"\x00" * 200, 422, "corrupt"),
    ],
    ids=["half", "header-only", "garbage-after-magic"],
)
def test_broken_jpegs_are_422(client: TestClient, camera: str, jpeg: bytes, mutate, status: int, fragment: str) -> None:  # type: ignore[no-untyped-def]
    response = client.post(f"/v1/cameras/{camera}/frames", content=mutate(jpeg), headers={"Content-Type": "image/jpeg"})
    assert_problem(response, status, fragment)


@pytest.mark.parametrize(
    "params",
    [[], [cv2.IMWRITE_JPEG_PROGRESSIVE, 1], [cv2.IMWRITE_JPEG_RST_INTERVAL, 4]],
    ids=["baseline", "progressive", "restart-markers"],
)
def test_a_jpeg_is_complete_at_its_end_marker_whatever_follows(params: list[int]) -> None:
    """Phones append to their JPEGs (a motion photo is the JPEG and then a video): the picture ends at its EOI."""
    rng = np.random.default_rng(1)
    picture = cv2.GaussianBlur(rng.integers(0, 255, (360, 640, 3), dtype=np.uint8), (0, 0), 2)
    ok, encoded_picture = cv2.imencode(".jpg", picture, params)
    assert ok
    data = encoded_picture.tobytes()
    video = b"\x00\x00\x00\x18ftypmp42" + rng.integers(0, 256, 50_000, dtype=np.uint8).tobytes()
    for complete in (data, data + b"\x00" * 100, data + video):
        header, image = decode(complete, max_pixels=10**6)
        assert (header.width_px, header.height_px) == (640, 360)
        assert np.array_equal(image, cv2.imdecode(encoded_picture, cv2.IMREAD_COLOR))
    for cut in (len(data) // 3, len(data) // 2, len(data) - 2, len(data) - 1):
        with pytest.raises(ImageError, match="truncated"):
            decode(data[:cut], max_pixels=10**6)
        with pytest.raises(ImageError, match="truncated"):  # cut, then bytes that hold no end marker
            decode(data[:cut] + b"\xff\x00" * 50, max_pixels=10**6)


def test_a_png_is_complete_at_its_iend_chunk_whatever_follows() -> None:
    data = _encoded_as(".png")
    for complete in (data, data + b"\x00" * 100, data + b"trailing bytes a tool appended"):
        header, image = decode(complete, max_pixels=10**6)
        assert (header.width_px, header.height_px, image.shape) == (48, 32, (32, 48, 3))
    for cut in (len(data) // 2, len(data) - 12, len(data) - 1):
        with pytest.raises(ImageError, match="truncated"):
            decode(data[:cut], max_pixels=10**6)


def test_a_motion_photo_is_accepted(client: TestClient, camera: str, jpeg: bytes, app: FastAPI) -> None:
    upload = jpeg + b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 40
    response = client.post(f"/v1/cameras/{camera}/frames", content=upload, headers={"Content-Type": "image/jpeg"})
    assert response.status_code == 202, response.text


def test_truncated_png_is_422(client: TestClient, camera: str, png: bytes) -> None:
    response = client.post(f"/v1/cameras/{camera}/frames", content=png[:-200], headers={"Content-Type": "image/png"})
    assert_problem(response, 422, "truncated png")


def test_decompression_bomb_is_refused_before_decoding(client: TestClient, camera: str) -> None:
    response = client.post(
        f"/v1/cameras/{camera}/frames", content=png_header_only(100_000, 100_000), headers={"Content-Type": "image/png"}
    )
    assert_problem(response, 413, "100000x100000", "max_image_pixels")


def test_image_of_another_size_is_422(client: TestClient, camera: str) -> None:
    response = client.post(
        f"/v1/cameras/{camera}/frames", content=encoded(".jpg", 640, 480), headers={"Content-Type": "image/jpeg"}
    )
    assert_problem(response, 422, "640x480", f"{WIDTH_PX}x{HEIGHT_PX}")


@pytest.mark.parametrize(
    ("orientation", "turn"),
    [(1, None), (3, cv2.ROTATE_180), (6, cv2.ROTATE_90_CLOCKWISE), (8, cv2.ROTATE_90_COUNTERCLOCKWISE)],
)
def test_a_jpeg_is_the_picture_its_exif_orientation_shows(orientation: int, turn: int | None) -> None:
    """A phone held upright stores the sensor's rows and an orientation: the picture is the one a viewer shows,
    and its size is the shown one (before, a turned JPEG was refused: it decoded to its size turned)."""
    rows = np.zeros((360, 640, 3), dtype=np.uint8)
    rows[:120, :200] = 255  # a white block in the stored top-left corner
    ok, data = cv2.imencode(".jpg", rows, [cv2.IMWRITE_JPEG_QUALITY, 100])
    assert ok
    header, image = decode(with_exif_orientation(data.tobytes(), orientation), max_pixels=10**6)
    expected = rows if turn is None else cv2.rotate(rows, turn)
    assert (header.width_px, header.height_px) == (expected.shape[1], expected.shape[0])
    assert image.shape == expected.shape and np.abs(image.astype(int) - expected).mean() < 2.0


def test_an_upright_phone_picture_goes_to_an_upright_camera(client: TestClient) -> None:
    portrait = client.put("/v1/cameras/phone", json={"image_width_px": 360, "image_height_px": 640})
    assert portrait.status_code == 201, portrait.text
    sideways = with_exif_orientation(encoded(".jpg", 640, 360), 6)  # 640 x 360 rows, shown 360 x 640
    response = client.post("/v1/cameras/phone/frames", content=sideways, headers={"Content-Type": "image/jpeg"})
    assert response.status_code == 202, response.text
    landscape = client.put("/v1/cameras/landscape", json={"image_width_px": 640, "image_height_px": 360})
    assert landscape.status_code == 201, landscape.text
    response = client.post("/v1/cameras/landscape/frames", content=sideways, headers={"Content-Type": "image/jpeg"})
    assert_problem(response, 422, "360x640", "640x360")


@pytest.mark.parametrize(
    ("content", "content_type", "status", "fragments"),
    [
        (b"", "image/jpeg", 422, ("empty",)),
        (b"hello", "text/plain", 415, ("image/jpeg", "text/plain")),
        (b"hello", "image/jpeg", 415, ("not a jpeg or png",)),
        (b'{"people": []}', "application/json", 415, ("multipart/form-data",)),
    ],
    ids=["empty", "text", "text-labelled-jpeg", "json"],
)
def test_wrong_bodies_are_4xx(
    client: TestClient, camera: str, content: bytes, content_type: str, status: int, fragments: tuple[str, ...]
) -> None:
    response = client.post(f"/v1/cameras/{camera}/frames", content=content, headers={"Content-Type": content_type})
    assert_problem(response, status, *fragments)


def test_mislabelled_image_is_415(client: TestClient, camera: str, jpeg: bytes) -> None:
    response = client.post(f"/v1/cameras/{camera}/frames", content=jpeg, headers={"Content-Type": "image/png"})
    assert_problem(response, 415, "declared image/png", "image/jpeg")


def _encoded_as(ext: str) -> bytes:
    ok, data = cv2.imencode(ext, np.zeros((32, 48, 3), dtype=np.uint8))
    assert ok
    return data.tobytes()


@pytest.mark.parametrize(
    ("name", "data"),
    [
        ("HEIC", b"\x00\x00\x00\x18ftypheic\x00\x00\x00\x00mif1heic" + b"\x00" * 64),
        ("AVIF", b"\x00\x00\x00\x1cftypavif\x00\x00\x00\x00avifmif1" + b"\x00" * 64),
        ("WebP", _encoded_as(".webp")),
        ("GIF", b"GIF89a" + b"\x00" * 64),
        ("TIFF", _encoded_as(".tiff")),
        ("BMP", _encoded_as(".bmp")),
    ],
)
def test_another_format_is_named_in_the_415(client: TestClient, camera: str, name: str, data: bytes) -> None:
    as_form = client.post(f"/v1/cameras/{camera}/frames", files={"image": ("photo", data, "application/octet-stream")})
    assert_problem(as_form, 415, f"a {name} image", "reads JPEG and PNG")
    mislabelled = client.post(f"/v1/cameras/{camera}/frames", content=data, headers={"Content-Type": "image/jpeg"})
    assert_problem(mislabelled, 415, f"a {name} image")


def test_multipart_without_image_field_is_422(client: TestClient, camera: str, jpeg: bytes) -> None:
    response = client.post(f"/v1/cameras/{camera}/frames", files={"picture": ("a.jpg", jpeg, "image/jpeg")})
    assert_problem(response, 422, "`image`")


def test_bad_query_fields_are_422(client: TestClient, camera: str, jpeg: bytes) -> None:
    headers = {"Content-Type": "image/jpeg"}
    assert_problem(client.post(f"/v1/cameras/{camera}/frames?timestamp=yesterday", content=jpeg, headers=headers), 422)
    assert_problem(client.post(f"/v1/cameras/{camera}/frames?frame_id=a%20b", content=jpeg, headers=headers), 422)


def test_oversize_image_is_413(client: TestClient, camera: str, app: FastAPI, jpeg: bytes) -> None:
    limit = app.state.settings.max_image_bytes
    response = client.post(
        f"/v1/cameras/{camera}/frames",
        content=b"\xff\xd8\xff" + b"\x00" * (limit + 70_000),
        headers={"Content-Type": "image/jpeg"},
    )
    assert_problem(response, 413, "max_image_bytes")


def test_unknown_camera_is_404(client: TestClient, jpeg: bytes) -> None:
    response = client.post("/v1/cameras/nope/frames", content=jpeg, headers={"Content-Type": "image/jpeg"})
    assert_problem(response, 404, "nope")


def test_queue_down_is_503_and_the_image_is_kept(
    client: TestClient, camera: str, jpeg: bytes, dispatcher: RecordingDispatcher, app: FastAPI
) -> None:
    dispatcher.fail = True
    response = client.post(f"/v1/cameras/{camera}/frames", content=jpeg, headers={"Content-Type": "image/jpeg"})
    body = assert_problem(response, 503, "stored")
    with app.state.session_factory() as session:
        assert frame_image(session, uuid.UUID(body["frame_id"])) is not None


@given(st.binary(max_size=2000))
@settings(max_examples=300, deadline=None)
def test_any_bytes_after_a_jpeg_signature_are_an_image_error_or_an_image(tail: bytes) -> None:
    try:
        header, image = decode(b"\xff\xd8\xff" + tail, max_pixels=10**6)
    except ImageError:
        return
    assert image.shape == (header.height_px, header.width_px, 3)
