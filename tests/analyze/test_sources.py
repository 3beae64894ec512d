"""Frame sources: a real video read with a stride, image folders in natural order, bad files skipped with a reason."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.analyze.errors import AnalyzeError
from service.analyze.sources import ImageSource, SkippedFrame, SourceFrame, VideoSource, open_source
from tests.support.analyze import TOWN_VIDEO, write_image


def test_video_with_stride_and_max_frames(town: Path) -> None:
    source = open_source(TOWN_VIDEO, stride=25, max_frames=4)
    assert isinstance(source, VideoSource)
    assert source.image_size_px == (1920, 1080) and source.fps == 25.0 and source.frame_count == 126
    assert source.planned() == 4
    frames = list(source.frames())
    assert [f.index for f in frames] == [0, 25, 50, 75]
    assert all(isinstance(f, SourceFrame) and f.image.shape == (1080, 1920, 3) for f in frames)
    assert [f.time_s for f in frames if isinstance(f, SourceFrame)] == [0.0, 1.0, 2.0, 3.0]
    # Read again (the pictures pass): the same frames.
    assert [f.index for f in source.frames()] == [0, 25, 50, 75]
    everything = open_source(TOWN_VIDEO, stride=50)
    assert everything.planned() == 3 and [f.index for f in everything.frames()] == [0, 50, 100]


def test_image_folder_natural_order_stride_and_skipped_files(tmp_path: Path) -> None:
    for name in ("f_10.png", "f_2.png", "f_1.jpg", "f_3.png", "f_4.png"):
        write_image(tmp_path / name)
    (tmp_path / "f_3.png").write_bytes((tmp_path / "f_3.png").read_bytes()[:-30])  # truncated
    write_image(tmp_path / "f_4.png", (64, 48))  # another size
    (tmp_path / "notes.txt").write_text("not an image")
    (tmp_path / ".hidden.png").write_bytes(b"")
    source = open_source(tmp_path)
    assert isinstance(source, ImageSource)
    assert [p.name for p in source.files] == ["f_1.jpg", "f_2.png", "f_3.png", "f_4.png", "f_10.png"]
    assert source.image_size_px == (320, 240) and source.fps is None
    items = list(source.frames())
    assert [type(i) for i in items] == [SourceFrame, SourceFrame, SkippedFrame, SkippedFrame, SourceFrame]
    assert "truncated" in items[2].reason and "320x240" in items[3].reason  # type: ignore[union-attr]
    strided = open_source(tmp_path, stride=2, max_frames=2)
    assert [(i.index, i.file) for i in strided.frames()] == [(0, "f_1.jpg"), (2, "f_3.png")]
    single = open_source(tmp_path / "f_2.png")
    assert [i.file for i in single.frames()] == ["f_2.png"]
    # A folder's own rate (`--fps`) gives its images their times, counted in the whole folder's steps.
    timed = open_source(tmp_path, stride=2, fps=0.5)
    assert timed.fps == 0.5 and [i.time_s for i in timed.frames() if isinstance(i, SourceFrame)] == [0.0, 8.0]


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda d: d / "missing.mp4", "does not exist"),
        (lambda d: d, "no images in"),
        (lambda d: (d / "clip.mp4").write_text("not a video") and d / "clip.mp4", "cannot read"),
        (lambda d: (d / "a.jpg").write_bytes(b"\xff\xd8\xff garbage") and d, "could be read"),
    ],
    ids=["missing", "empty folder", "unreadable video", "only unreadable images"],
)
def test_bad_sources_are_one_clear_error(tmp_path: Path, make, message: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(AnalyzeError, match=message):
        open_source(make(tmp_path))


def test_a_frame_rate_is_for_image_folders_and_positive(tmp_path: Path, town: Path) -> None:
    write_image(tmp_path / "a.png")
    for fps in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(AnalyzeError, match="positive number of images per second"):
            open_source(tmp_path, fps=fps)
    with pytest.raises(AnalyzeError, match="--fps is for a folder of images"):
        open_source(TOWN_VIDEO, fps=25.0)
