"""`companion horizon stream --rerun-save`: frames and the detected line, read back with rerun."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import rerun as rr
from conftest import free_udp_port

from companion.cli import main
from horizon.synth import SceneSpec, render_scene


def test_stream_writes_frames_and_horizon_to_rrd(tmp_path: Path) -> None:
    video = tmp_path / "flight.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (320, 240))
    assert writer.isOpened()
    rng = np.random.default_rng(0)
    for k in range(12):
        image, _line = render_scene(SceneSpec(width=320, height=240, roll_deg=5.0 + k,
                                              offset_frac=0.05), rng)
        writer.write(image)
    writer.release()
    out = tmp_path / "horizon.rrd"
    assert main(["horizon", "stream", str(video), "--hfov-deg", "60",
                 "--legacy", f"127.0.0.1:{free_udp_port()}", "--rerun-save", str(out)]) == 0
    rows: dict[str, int] = {}
    for chunk in rr.chunk.RrdReader(out).stream():
        if not chunk.is_static:
            rows[str(chunk.entity_path)] = rows.get(str(chunk.entity_path), 0) + chunk.num_rows
    assert rows.get("/camera/image", 0) >= 1
    assert rows.get("/camera/image/horizon", 0) >= 1
    assert np.isfinite(list(rows.values())).all()
