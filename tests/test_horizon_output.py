"""CSV rows and overlays."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import cv2
import numpy as np
import pytest

from horizon.camera import CameraModel
from horizon.estimate import HorizonEstimate
from horizon.geometry import OrientedLine
from horizon.output import (
    CSV_COLUMNS,
    CsvSink,
    OutputError,
    OverlayFrames,
    OverlayVideo,
    draw_overlay,
)


def _found() -> HorizonEstimate:
    return HorizonEstimate.from_line(OrientedLine.from_roll_offset(10.0, 0.1, 320, 240), 0.8, "robust")


def test_csv_rows() -> None:
    buf = io.StringIO()
    sink = CsvSink(buf)
    sink.write("a.png", _found())
    sink.write("7", HorizonEstimate.none("robust", 320, 240, 0.1))
    rows = list(csv.DictReader(io.StringIO(buf.getvalue())))
    assert tuple(rows[0]) == CSV_COLUMNS
    assert rows[0]["found"] == "1" and float(rows[0]["roll_deg"]) == pytest.approx(10.0)
    assert float(rows[0]["offset_frac"]) == pytest.approx(0.1)
    assert float(rows[0]["x1"]) == pytest.approx(0.0) and rows[0]["pitch_deg"] == ""
    assert rows[1]["image"] == "7" and rows[1]["found"] == "0" and rows[1]["x1"] == ""


def test_csv_to_unwritable_path(tmp_path: Path) -> None:
    with pytest.raises(OutputError, match="cannot write CSV"):
        CsvSink(tmp_path / "missing" / "out.csv")


def test_overlay_draws_the_line() -> None:
    img = np.zeros((240, 320, 3), np.uint8)
    est = _found()
    out = draw_overlay(img, est)
    assert out.shape == img.shape and not np.array_equal(out, img)
    assert est.p1 is not None and est.p2 is not None
    (x1, y1), (x2, y2) = est.p1, est.p2
    x = 80
    y = int(round(y1 + (y2 - y1) * (x - x1) / (x2 - x1)))
    assert out[y - 2 : y + 3, x, 2].max() > 200  # the red line
    lens = CameraModel.from_hfov(320, 240, 70.0, k1=-0.15)
    assert not np.array_equal(draw_overlay(img, est, lens), out)  # bent by the lens
    assert draw_overlay(img, HorizonEstimate.none("robust", 320, 240)).any()  # "no horizon" text


def test_overlay_frames_and_video(tmp_path: Path) -> None:
    frames = OverlayFrames(tmp_path / "ov")
    img = np.zeros((48, 64, 3), np.uint8)
    p1 = frames.write("/data/x/a.jpg", 0, img)
    p2 = frames.write("/other/a.jpg", 1, img)
    p3 = frames.write("12", 12, img)
    assert p1.name == "a.png" and p2.name == "a_2.png" and p3.name == "frame_000012.png"
    video = OverlayVideo(tmp_path / "ov.avi", fps=10)
    for _ in range(3):
        video.write(img)
    video.write(np.zeros((20, 20, 3), np.uint8))  # other sizes are scaled
    video.close()
    cap = cv2.VideoCapture(str(tmp_path / "ov.avi"))
    try:
        n = 0
        while cap.read()[0]:
            n += 1
    finally:
        cap.release()
    assert n == 4
