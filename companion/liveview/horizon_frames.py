"""Camera frames and the detected horizon into rerun, on the live view's entity paths.

`companion horizon stream --rerun-save PATH` (or `--rerun`) writes what the detector saw next to
the flight's own live view: same application, same `flight_time` timeline, `camera/image` and
`camera/image/horizon`, so the two recordings line up in one viewer. It lives on the companion
side so that the horizon library imports nothing of the companion: the main CLI hands this class
to `horizon.cli.add_commands`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from companion.liveview import entities as E
from companion.liveview.sink import open_recording
from horizon.estimate import HorizonEstimate

FRAME_EVERY_S = 0.1  # at most 10 frames a second go to the viewer: images are large


class RerunFrames:
    def __init__(self, *, spawn: bool = False, save_path: Path | None = None) -> None:
        self._e = E
        self.recording = open_recording(spawn=spawn, save_path=save_path)
        self._last_ns = 0
        self.frames = 0

    def __call__(self, image: np.ndarray, est: HorizonEstimate, t_ns: int) -> None:
        import rerun as rr

        if t_ns - self._last_ns < FRAME_EVERY_S * 1e9:
            return
        self._last_ns = t_ns
        stream = self.recording.stream
        stream.set_time(self._e.TIMELINE, timestamp=np.datetime64(int(t_ns), "ns"))
        rgb = image[..., ::-1] if image.ndim == 3 else image  # OpenCV frames are BGR
        stream.log(self._e.CAMERA_IMAGE, rr.Image(rgb))
        if est.found and est.p1 is not None and est.p2 is not None:
            stream.log(self._e.CAMERA_HORIZON,
                       rr.LineStrips2D([[est.p1, est.p2]], colors=[[255, 200, 0]], radii=1.5))
        else:
            stream.log(self._e.CAMERA_HORIZON, rr.Clear(recursive=False))
        self.frames += 1

    def close(self) -> None:
        self.recording.close()
