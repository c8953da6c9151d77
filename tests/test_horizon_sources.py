"""Frame sources: files, folders, videos; clear errors for what cannot be read."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from horizon.sources import FrameSourceError, iter_frames, parse_input


def _write_video(path: Path, n: int = 5) -> None:
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 10.0, (64, 48))
    assert vw.isOpened()
    for i in range(n):
        vw.write(np.full((48, 64, 3), 20 * i, np.uint8))
    vw.release()


def test_image_folder_and_video(tmp_path: Path) -> None:
    img = np.full((30, 40, 3), 100, np.uint8)
    cv2.imwrite(str(tmp_path / "b.png"), img)
    cv2.imwrite(str(tmp_path / "a.jpg"), img)
    (tmp_path / "notes.txt").write_text("not an image")
    video = tmp_path / "clip.avi"
    _write_video(video)
    frames = list(iter_frames([str(tmp_path), str(tmp_path / "b.png"), str(video)]))
    labels = [f.label for f in frames]
    assert labels[:3] == [str(tmp_path / "a.jpg"), str(tmp_path / "b.png"), str(tmp_path / "b.png")]
    assert labels[3:] == ["0", "1", "2", "3", "4"]
    assert all(f.image.dtype == np.uint8 and f.image.ndim == 3 for f in frames)
    assert list(iter_frames([str(video)], max_frames=2))[-1].label == "1"


def test_missing_input_is_named() -> None:
    with pytest.raises(FrameSourceError, match="no_such.png: no such file"):
        parse_input("no_such.png")
    assert parse_input("camera:2").camera_index == 2
    assert parse_input("0").kind == "camera"


def test_undecodable_image_is_reported_and_skipped(tmp_path: Path) -> None:
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"\xff\xd8\xff\xe0garbage")
    good = tmp_path / "good.png"
    cv2.imwrite(str(good), np.zeros((8, 8, 3), np.uint8))
    errors: list[str] = []
    frames = list(iter_frames([str(bad), str(good)], on_error=errors.append))
    assert [f.label for f in frames] == [str(good)]
    assert len(errors) == 1 and str(bad) in errors[0]
    with pytest.raises(FrameSourceError, match="bad.jpg"):
        list(iter_frames([str(bad)]))


def test_huge_image_header_is_refused_before_decoding(tmp_path: Path) -> None:
    # a valid PNG signature and IHDR announcing 100000 x 100000 pixels
    ihdr = struct.pack(">IIBBBBB", 100_000, 100_000, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    p = tmp_path / "bomb.png"
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk)
    with pytest.raises(FrameSourceError, match="100000x100000"):
        list(iter_frames([str(p)]))


def test_unreadable_video_is_named(tmp_path: Path) -> None:
    p = tmp_path / "broken.mp4"
    p.write_bytes(b"\x00" * 100)
    errors: list[str] = []
    assert list(iter_frames([str(p)], on_error=errors.append)) == []
    assert errors and "broken.mp4" in errors[0]


def test_empty_folder(tmp_path: Path) -> None:
    with pytest.raises(FrameSourceError, match="no image files"):
        list(iter_frames([str(tmp_path)]))
