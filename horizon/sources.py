"""Where frames come from: image files, folders of images, video files and cameras.

Every input string becomes a stream of :class:`Frame`; a folder is read in name order, a video or
camera frame by frame through ``cv2.VideoCapture``. Inputs are checked before anything is read, so
a typo fails at once with the path in the message. Images whose header announces more than
:data:`MAX_IMAGE_PIXELS` are refused before decoding, so a hostile file cannot make us allocate
gigabytes.
"""

from __future__ import annotations

import logging
import re
import struct
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = [
    "Frame",
    "FrameSourceError",
    "InputSpec",
    "parse_input",
    "iter_frames",
    "IMAGE_EXTENSIONS",
    "MAX_IMAGE_PIXELS",
]

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = frozenset(
    {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm", ".pnm"}
)
MAX_IMAGE_PIXELS = 50_000_000
_CAMERA = re.compile(r"^(?:cam(?:era)?:)?(\d{1,3})$")


class FrameSourceError(Exception):
    """An input that cannot be read; the message names it."""


@dataclass(frozen=True)
class Frame:
    """One frame: ``label`` is the image path, or the frame number for a video or camera;
    ``time_ns`` is when it was captured or read (Unix time, nanoseconds)."""

    label: str
    index: int
    image: NDArray[np.uint8]
    time_ns: int
    source: str


@dataclass(frozen=True)
class InputSpec:
    kind: str  # "image", "folder", "video" or "camera"
    text: str
    path: Path | None = None
    camera_index: int = -1


def parse_input(text: str) -> InputSpec:
    """Classify one input string, failing with a clear message when it names nothing."""
    p = Path(text)
    if p.is_dir():
        return InputSpec("folder", text, p)
    if p.is_file():
        kind = "image" if p.suffix.lower() in IMAGE_EXTENSIONS else "video"
        return InputSpec(kind, text, p)
    m = _CAMERA.match(text)
    if m:
        return InputSpec("camera", text, camera_index=int(m.group(1)))
    if p.exists():
        raise FrameSourceError(f"{text}: neither a file nor a folder")
    raise FrameSourceError(f"{text}: no such file or folder (cameras are written camera:N)")


def iter_frames(
    inputs: Sequence[str],
    on_error: Callable[[str], None] | None = None,
    max_frames: int | None = None,
) -> Iterator[Frame]:
    """Frames of every input in order. A file that cannot be decoded is reported through
    ``on_error`` and skipped (without ``on_error`` it raises :class:`FrameSourceError`)."""
    specs = [parse_input(t) for t in inputs]
    count = 0
    for spec in specs:
        for frame in _frames_of(spec, on_error):
            yield frame
            count += 1
            if max_frames is not None and count >= max_frames:
                return


def _report(on_error: Callable[[str], None] | None, message: str) -> None:
    if on_error is None:
        raise FrameSourceError(message)
    on_error(message)


def _frames_of(spec: InputSpec, on_error: Callable[[str], None] | None) -> Iterator[Frame]:
    if spec.kind == "image":
        assert spec.path is not None
        img = _read_image(spec.path, on_error)
        if img is not None:
            yield Frame(str(spec.path), 0, img, time.time_ns(), spec.text)
    elif spec.kind == "folder":
        assert spec.path is not None
        files = sorted(
            f for f in spec.path.iterdir() if f.is_file() and f.suffix.lower() in IMAGE_EXTENSIONS
        )
        if not files:
            _report(on_error, f"{spec.path}: no image files ({', '.join(sorted(IMAGE_EXTENSIONS))})")
        for i, f in enumerate(files):
            img = _read_image(f, on_error)
            if img is not None:
                yield Frame(str(f), i, img, time.time_ns(), spec.text)
    else:
        yield from _capture(spec, on_error)


def _capture(spec: InputSpec, on_error: Callable[[str], None] | None) -> Iterator[Frame]:
    source: str | int = str(spec.path) if spec.path is not None else spec.camera_index
    cap = cv2.VideoCapture(source)
    try:
        if not cap.isOpened():
            what = "camera" if spec.kind == "camera" else "video (unknown format or unreadable)"
            _report(on_error, f"{spec.text}: cannot open as a {what}")
            return
        index = 0
        while True:
            ok, img = cap.read()
            t_ns = time.time_ns()
            if not ok or img is None:
                break
            if img.dtype != np.uint8:
                img = cv2.convertScaleAbs(img)
            yield Frame(str(index), index, np.asarray(img, np.uint8), t_ns, spec.text)
            index += 1
        if index == 0:
            _report(on_error, f"{spec.text}: no frame could be decoded")
    finally:
        cap.release()


def _read_image(path: Path, on_error: Callable[[str], None] | None) -> NDArray[np.uint8] | None:
    try:
        size = _peek_size(path)
    except OSError as exc:
        _report(on_error, f"{path}: cannot read: {exc.strerror or exc}")
        return None
    if size is not None and size[0] * size[1] > MAX_IMAGE_PIXELS:
        _report(
            on_error,
            f"{path}: image header says {size[0]}x{size[1]} pixels, over the limit of "
            f"{MAX_IMAGE_PIXELS}",
        )
        return None
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        _report(on_error, f"{path}: not a decodable image")
        return None
    return np.asarray(img, np.uint8)


def _peek_size(path: Path) -> tuple[int, int] | None:
    """Width and height from a PNG or JPEG header without decoding; None for other formats or
    when the header cannot be understood (the decoder then has the last word)."""
    with path.open("rb") as f:
        head = f.read(32)
        if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) >= 24:
            w, h = struct.unpack(">II", head[16:24])
            return int(w), int(h)
        if head[:2] != b"\xff\xd8":
            return None
        # walk the JPEG markers up to the frame header (SOFn); bounded by the file size
        f.seek(2)
        for _ in range(10_000):
            marker = f.read(2)
            if len(marker) < 2 or marker[0] != 0xFF:
                return None
            code = marker[1]
            if code in (0xD8, 0x01) or 0xD0 <= code <= 0xD7:
                continue
            seg = f.read(2)
            if len(seg) < 2:
                return None
            length = struct.unpack(">H", seg)[0]
            if 0xC0 <= code <= 0xCF and code not in (0xC4, 0xC8, 0xCC):
                sof = f.read(5)
                if len(sof) < 5:
                    return None
                h, w = struct.unpack(">HH", sof[1:5])
                return int(w), int(h)
            if length < 2:
                return None
            f.seek(length - 2, 1)
    return None
