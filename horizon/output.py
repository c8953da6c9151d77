"""Writing results: one CSV row per frame, and frames or a video with the horizon drawn in."""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path
from typing import IO

import cv2
import numpy as np
from numpy.typing import NDArray

from horizon.camera import CameraModel
from horizon.estimate import HorizonEstimate

__all__ = [
    "CSV_COLUMNS",
    "CsvSink",
    "csv_row",
    "draw_overlay",
    "OverlayFrames",
    "OverlayVideo",
    "OutputError",
]

CSV_COLUMNS = (
    "image",
    "found",
    "x1",
    "y1",
    "x2",
    "y2",
    "roll_deg",
    "offset_frac",
    "pitch_deg",
    "quality",
    "method",
)

SKY_BGR = (255, 200, 0)
LINE_BGR = (0, 0, 255)
TEXT_BGR = (255, 255, 255)


class OutputError(Exception):
    """An output that cannot be written; the message names it."""


def _num(x: float | None, digits: int) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return ""
    return f"{x:.{digits}f}"


def csv_row(label: str, est: HorizonEstimate) -> list[str]:
    """The CSV cells for one frame; geometric cells are empty when no horizon was found."""
    p1 = est.p1 if est.found else None
    p2 = est.p2 if est.found else None
    return [
        label,
        "1" if est.found else "0",
        _num(p1[0] if p1 else None, 3),
        _num(p1[1] if p1 else None, 3),
        _num(p2[0] if p2 else None, 3),
        _num(p2[1] if p2 else None, 3),
        _num(est.roll_deg, 4),
        _num(est.offset_frac, 6),
        _num(est.pitch_deg, 4),
        _num(est.quality, 4),
        est.method,
    ]


class CsvSink:
    """CSV writer to a path or an open text stream; each row is flushed, so a long video run can
    be followed with ``tail -f``."""

    def __init__(self, target: str | Path | IO[str]) -> None:
        self._own = False
        if isinstance(target, str | Path):
            path = Path(target)
            try:
                self._file: IO[str] = path.open("w", newline="", encoding="utf-8")
            except OSError as exc:
                raise OutputError(f"{path}: cannot write CSV: {exc.strerror or exc}") from None
            self._own = True
        else:
            self._file = target
        self._writer = csv.writer(self._file, lineterminator="\n")
        self._writer.writerow(CSV_COLUMNS)
        self.rows = 0

    def write(self, label: str, est: HorizonEstimate) -> None:
        self._writer.writerow(csv_row(label, est))
        self._file.flush()
        self.rows += 1

    def close(self) -> None:
        if self._own:
            self._file.close()

    def __enter__(self) -> CsvSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def draw_overlay(
    image: NDArray[np.uint8], est: HorizonEstimate, camera: CameraModel | None = None
) -> NDArray[np.uint8]:
    """A copy of ``image`` with the horizon drawn (bent through the lens model when one is given,
    since the line is straight only in undistorted coordinates), a tick on the sky side and the
    numbers; or "no horizon"."""
    out = np.asarray(image.copy() if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), np.uint8)
    h, w = out.shape[:2]
    scale = max(0.4, min(w, h) / 480.0)
    thick = max(1, round(2 * scale))
    if est.found and est.p1 is not None and est.p2 is not None:
        p1, p2 = np.array(est.p1), np.array(est.p2)
        pts = p1[None, :] + np.linspace(0.0, 1.0, 64)[:, None] * (p2 - p1)[None, :]
        if camera is not None and camera.has_distortion:
            pts = camera.scaled_to(w, h).distort_points(pts)
        cv2.polylines(out, [np.rint(pts).astype(np.int32).reshape(-1, 1, 2)], False, LINE_BGR, thick, cv2.LINE_AA)
        # a short tick from the middle of the line towards the sky
        mid = 0.5 * (p1 + p2)
        d = (p2 - p1) / (np.linalg.norm(p2 - p1) + 1e-9)
        sky = np.array([d[1], -d[0]])
        tip = mid + sky * 0.06 * min(w, h)
        ends = np.array([mid, tip])
        if camera is not None and camera.has_distortion:
            ends = camera.scaled_to(w, h).distort_points(ends)
        a, b = np.rint(ends).astype(int)
        cv2.line(out, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), SKY_BGR, thick, cv2.LINE_AA)
        text = f"roll {est.roll_deg:+.1f}  off {100 * (est.offset_frac or 0.0):+.1f}%"
        if est.pitch_deg is not None:
            text += f"  pitch {est.pitch_deg:+.1f}"
        text += f"  q {est.quality:.2f}"
    else:
        text = f"no horizon  q {est.quality:.2f}"
    org = (max(4, round(6 * scale)), max(14, round(22 * scale)))
    cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.5 * scale, (0, 0, 0), thick + 2, cv2.LINE_AA)
    cv2.putText(out, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.5 * scale, TEXT_BGR, thick, cv2.LINE_AA)
    return out


def _safe_name(label: str, index: int) -> str:
    stem = Path(label).stem if not label.isdigit() else f"frame_{int(label):06d}"
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", stem)[:120] or f"frame_{index:06d}"
    return stem


class OverlayFrames:
    """Overlay images into a folder, one PNG per frame, named after the input image (or the
    frame number); names that repeat across inputs get a counter."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{self.folder}: cannot create overlay folder: {exc.strerror or exc}") from None
        self._used: set[str] = set()
        self.written = 0

    def write(self, label: str, index: int, image: NDArray[np.uint8]) -> Path:
        name = _safe_name(label, index)
        base, n = name, 1
        while name in self._used:
            n += 1
            name = f"{base}_{n}"
        self._used.add(name)
        path = self.folder / f"{name}.png"
        if not cv2.imwrite(str(path), image):
            raise OutputError(f"{path}: cannot write overlay image")
        self.written += 1
        return path


class OverlayVideo:
    """Overlay frames into one video file (MJPG in .avi, mp4v otherwise); the size is fixed by
    the first frame and later frames of another size are scaled to it."""

    def __init__(self, path: str | Path, fps: float = 25.0) -> None:
        self.path = Path(path)
        self.fps = fps
        self._writer: cv2.VideoWriter | None = None
        self._size: tuple[int, int] | None = None
        self.written = 0

    def write(self, image: NDArray[np.uint8]) -> None:
        h, w = image.shape[:2]
        if self._writer is None:
            fourcc = "MJPG" if self.path.suffix.lower() == ".avi" else "mp4v"
            writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter.fourcc(*fourcc), self.fps, (w, h))
            if not writer.isOpened():
                raise OutputError(f"{self.path}: cannot open video for writing ({fourcc})")
            self._writer, self._size = writer, (w, h)
        if self._size is not None and (w, h) != self._size:
            image = np.asarray(cv2.resize(image, self._size, interpolation=cv2.INTER_AREA), np.uint8)
        self._writer.write(image)
        self.written += 1

    def close(self) -> None:
        if self._writer is not None:
            self._writer.release()
            self._writer = None
