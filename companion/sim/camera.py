"""A simulated forward-looking camera: frames rendered at the true attitude, the real detector.

Why: the estimator's horizon aiding was evaluated with "truth plus 1 deg of white noise", which
says nothing about what the detector does to it (frames without a horizon, gross errors in
glare or under sync stripes, latency). Here each frame is rendered with the ``horizon``
package's synthetic generator at the aircraft's true roll and pitch, disturbed as the thesis's
radio video link disturbed it, and handed to the same detector (and tracker) that
``companion horizon stream`` runs; its line becomes roll and pitch through the camera model,
as on the ground station. Failures are counted, never hidden.

Mounting: the camera looks forward along body x, image x (right) along body y, image y (down)
along body z, no tilt. For a pinhole camera the horizon is then the image line
``sin(roll) u + cos(roll) v = tan(pitch)`` in normalised coordinates ``(u, v)``: counter-
clockwise in the image for a right bank, below the principal point when the nose is up, which
is the convention of ``horizon.estimate.HorizonEstimate`` (checked by a test).

Rendering: a scene is rendered once, upright, as a large panorama with the horizon on its
middle row (``horizon.synth.render_scene``); each frame is a rotation and shift of it, which is
how ``render_scene`` itself places the horizon, at a fraction of the cost (a frame costs one
``warpAffine`` instead of a full render). Yaw, altitude and the dip of the real horizon below
the horizontal (about 0.5 deg at 300 m) are not rendered: the synthetic earth is flat and far.

Two ways to use it:

* offline, tick by tick (:class:`OfflineCameraFeed`, :func:`horizon_measurements`): the
  ``HorizonMeasurement`` handed off in each IMU tick, for ``companion.evaluation.sitl``;
* live, in the world (`companion.sim.world_camera`): a camera thread renders and detects, and
  at ``frame time + latency`` the estimate goes to the runtime as the legacy HORIZON_ATTITUDE
  datagram, where the legacy adapter writes it to ``state.horizon`` and the estimator thread
  fuses it. That module owns the thread, the hand-off on the world's clock and the links; this
  one the camera, its failure accounting and the offline feed.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.core.state import HorizonMeasurement
from horizon import synth
from horizon.camera import CameraModel
from horizon.detector import Detector, create_detector
from horizon.estimate import HorizonEstimate
from horizon.geometry import OrientedLine, wrap_deg
from horizon.tracking import HorizonTracker

log = logging.getLogger(__name__)

__all__ = [
    "DISTURBANCE_LEVELS",
    "SCENES",
    "CameraResult",
    "CameraStats",
    "OfflineCameraFeed",
    "SimCamera",
    "camera_seed",
    "default_camera_model",
    "horizon_measurements",
]

DISTURBANCE_LEVELS = ("none", "light", "thesis")
SCENES = ("fixed", "varying")
WIDTH_PX = 160
HEIGHT_PX = 120
HFOV_DEG = 70.0
RATE_HZ = 10.0
LATENCY_S = 0.1
"""Frame time to hand-off: detection on the ground plus the video and telemetry links."""
SCENE_CHANGE_S = 30.0
GROSS_ROLL_DEG = 10.0
GROSS_PITCH_DEG = 5.0
"""A detection this far from the truth is a gross error (about 10 % of the frame height in
pitch, the horizon benchmark's threshold)."""
SOURCE = "sim_camera"


def camera_seed(flight_seed: int) -> np.random.Generator:
    """The camera's generator for a flight seed: its own stream, so a flight with the camera
    draws every other sensor's noise as one without it (offline and live alike)."""
    return np.random.default_rng([flight_seed, 0x48_5A_4E])


def default_camera_model() -> CameraModel:
    """160x120, 70 deg horizontal field of view, no distortion: the detector works on a copy of
    about 120 px anyway, and a frame renders and detects in a few ms (bench/horizon_sitl_bench)."""
    return CameraModel.from_hfov(WIDTH_PX, HEIGHT_PX, HFOV_DEG)


@dataclass(frozen=True)
class CameraResult:
    """One frame: the truth it was rendered at, the detector's answer, what it cost.

    ``failed`` is True when the detector found no horizon or one it would not vouch for
    (quality 0); then ``roll_rad``/``pitch_rad`` are NaN and nothing is sent. ``gross`` marks a
    detection far from the truth: it *is* sent, as on the aircraft, where nobody knows it.
    """

    index: int
    t_s: float
    handoff_s: float
    roll_true_rad: float
    pitch_true_rad: float
    estimate: HorizonEstimate
    failed: bool
    roll_rad: float
    pitch_rad: float
    quality: float
    disturbances: tuple[str, ...]
    cost_s: float
    """Host seconds (wall clock) to render, disturb and detect this frame."""
    cpu_s: float = 0.0
    """CPU seconds of the calling thread for the same (OpenCV's own threads not included)."""
    in_view: bool = True
    """The true horizon crosses the frame: a failure then is a miss, a detection otherwise
    a false one."""

    @property
    def roll_error_rad(self) -> float:
        return math.radians(wrap_deg(math.degrees(self.roll_rad - self.roll_true_rad)))

    @property
    def pitch_error_rad(self) -> float:
        return self.pitch_rad - self.pitch_true_rad

    @property
    def gross(self) -> bool:
        return not self.failed and (
            abs(math.degrees(self.roll_error_rad)) > GROSS_ROLL_DEG
            or abs(math.degrees(self.pitch_error_rad)) > GROSS_PITCH_DEG)

    def measurement(self, frame_t_ns: int, source: str = SOURCE) -> HorizonMeasurement | None:
        """What the estimator receives (the frame's time in the receiver's clock), or None."""
        if self.failed:
            return None
        return HorizonMeasurement(frame_t_ns, self.roll_rad, self.pitch_rad, self.quality, source)


@dataclass
class CameraStats:
    """Counts and errors against the truth, for the report of a run."""

    frames: int = 0
    detections: int = 0
    failures: int = 0
    gross: int = 0
    in_view: int = 0
    """Frames with the true horizon in view."""
    missed: int = 0
    """Failures with the horizon in view (the others are right: nothing to see)."""
    false_detections: int = 0
    """Detections with no horizon in view."""
    dropped: int = 0
    """Frames the live camera skipped because the previous one was still being detected."""
    sent: int = 0
    send_errors: int = 0
    roll_err_deg: list[float] = field(default_factory=list)
    pitch_err_deg: list[float] = field(default_factory=list)
    cost_ms: list[float] = field(default_factory=list)
    cpu_ms: list[float] = field(default_factory=list)

    def add(self, r: CameraResult) -> None:
        self.frames += 1
        self.in_view += int(r.in_view)
        self.cost_ms.append(r.cost_s * 1e3)
        self.cpu_ms.append(r.cpu_s * 1e3)
        if r.failed:
            self.failures += 1
            self.missed += int(r.in_view)
            return
        self.detections += 1
        self.gross += int(r.gross)
        self.false_detections += int(not r.in_view)
        self.roll_err_deg.append(abs(math.degrees(r.roll_error_rad)))
        self.pitch_err_deg.append(abs(math.degrees(r.pitch_error_rad)))

    def summary(self) -> dict[str, Any]:
        """Rates in % of frames, errors (deg) over detections, cost (ms) per frame: wall
        clock and the thread's CPU time (the figure that does not depend on other load)."""

        def pct(values: list[float], q: float) -> float | None:
            return round(float(np.percentile(values, q)), 3) if values else None

        n = max(self.frames, 1)
        return {
            "frames": self.frames, "detections": self.detections, "failures": self.failures,
            "failure_pct": round(100.0 * self.failures / n, 2),
            "gross": self.gross, "gross_pct": round(100.0 * self.gross / n, 2),
            "in_view_pct": round(100.0 * self.in_view / n, 2),
            "missed": self.missed, "missed_pct": round(100.0 * self.missed / n, 2),
            "false_detections": self.false_detections,
            "dropped": self.dropped, "sent": self.sent, "send_errors": self.send_errors,
            "roll_err_med_deg": pct(self.roll_err_deg, 50),
            "roll_err_p95_deg": pct(self.roll_err_deg, 95),
            "pitch_err_med_deg": pct(self.pitch_err_deg, 50),
            "pitch_err_p95_deg": pct(self.pitch_err_deg, 95),
            "cost_med_ms": pct(self.cost_ms, 50), "cost_p95_ms": pct(self.cost_ms, 95),
            "cpu_med_ms": pct(self.cpu_ms, 50), "cpu_p95_ms": pct(self.cpu_ms, 95),
        }


# ---------------------------------------------------------------------------------------------
# disturbances: what the radio video link did to the frames


def _disturb(level: str, img: NDArray[np.uint8], rng: np.random.Generator,
             truth: OrientedLine) -> tuple[NDArray[np.uint8], tuple[str, ...]]:
    """``light``: a clean digital link (a little grain, an occasional exposure swing).
    ``thesis``: the 2003 analogue link as chapter 6.2.3 describes it: noise on every frame,
    sync stripes, exposure and colour swings and glare on some. The rates are our assumption
    (the thesis gives none); the strengths are ``horizon.synth``'s."""
    applied: list[str] = []
    if level == "light":
        img = synth.add_noise(img, rng, float(rng.uniform(0.05, 0.2)))
        applied.append("noise")
        if rng.random() < 0.2:
            img = synth.shift_exposure(img, float(rng.uniform(0.8, 1.25)))
            applied.append("exposure")
    elif level == "thesis":
        img = synth.add_noise(img, rng, float(rng.uniform(0.2, 0.5)))
        applied.append("noise")
        for name, prob in (("stripes", 0.15), ("black-stripes", 0.15), ("exposure", 0.15),
                           ("colour", 0.1), ("glare", 0.1)):
            if rng.random() < prob:
                img = synth.apply_disturbance(name, img, rng, truth)
                applied.append(name)
    return img, tuple(applied)


# ---------------------------------------------------------------------------------------------
# the camera


class SimCamera:
    """Renders a frame at the true attitude and runs the real detector on it.

    Deterministic for a seed: the scene and every frame's disturbances come from generators
    seeded by ``(seed, scene number)`` and ``(seed, frame number)``, so a frame does not depend
    on how many frames were dropped before it. ``scene`` ``fixed`` keeps one scene for the
    flight; ``varying`` draws a new one every ``scene_change_s`` of frame time.
    """

    def __init__(
        self,
        seed: int | np.random.Generator = 0,
        camera: CameraModel | None = None,
        *,
        rate_hz: float = RATE_HZ,
        latency_s: float = LATENCY_S,
        disturbance: str = "light",
        scene: str = "fixed",
        scene_change_s: float = SCENE_CHANGE_S,
        clutter: bool = False,
        method: str = "robust",
        track: bool = True,
    ) -> None:
        if disturbance not in DISTURBANCE_LEVELS:
            raise ValueError(f"SimCamera: disturbance must be one of {DISTURBANCE_LEVELS}, "
                             f"got {disturbance!r}")
        if scene not in SCENES:
            raise ValueError(f"SimCamera: scene must be one of {SCENES}, got {scene!r}")
        for name, value, lo, hi in (("rate_hz", rate_hz, 0.1, 100.0),
                                    ("latency_s", latency_s, 0.0, 2.0),
                                    ("scene_change_s", scene_change_s, 1.0, 1e6)):
            if not (math.isfinite(value) and lo <= value <= hi):
                raise ValueError(f"SimCamera: {name} must be within {lo}..{hi}, got {value!r}")
        self.camera = camera if camera is not None else default_camera_model()
        cam = self.camera
        if not math.isclose(cam.fx_px, cam.fy_px, rel_tol=1e-6):
            raise ValueError("SimCamera: the renderer needs square pixels (fx == fy)")
        self.seed = (int(seed.integers(2**63)) if isinstance(seed, np.random.Generator)
                     else int(seed))
        self.rate_hz = float(rate_hz)
        self.latency_s = float(latency_s)
        self.disturbance = disturbance
        self.scene = scene
        self.scene_change_s = float(scene_change_s)
        self.clutter = clutter
        detector: Detector = create_detector(method, cam)
        self._detect: Callable[[NDArray[np.uint8]], HorizonEstimate] = detector.detect
        if track and detector.name == "robust":  # as `companion horizon stream` does by default
            self._detect = HorizonTracker(detector).update  # type: ignore[arg-type]
        self.stats = CameraStats()
        self._period_s = 1.0 / self.rate_hz
        self._next_frame = 0
        self._index = 0
        self._scene_no = -1
        self._pano: NDArray[np.uint8] | None = None
        self._margin = self._lens_margin_px()
        half_diag = 0.5 * math.hypot(cam.width + 2 * self._margin[0],
                                     cam.height + 2 * self._margin[1])
        # beyond this the frame holds no horizon; clamping keeps the crop inside the panorama
        self._rho_max_px = half_diag + 0.25 * cam.height
        self._pano_side = 2 * int(math.ceil(self._rho_max_px + half_diag)) + 9

    # -- schedule ---------------------------------------------------------------------------

    def frame_due(self, t_s: float) -> int | None:
        """The number of the frame due at ``t_s`` (s of flight time), or None. Frames fall at
        ``(n + 1/2) / rate``; a caller that skips ahead gets the latest frame only."""
        n = int(math.floor(t_s * self.rate_hz - 0.5 + 1e-9))
        if n < self._next_frame:
            return None
        self._next_frame = n + 1
        return n

    # -- one frame --------------------------------------------------------------------------

    def truth_line(self, roll_rad: float, pitch_rad: float) -> OrientedLine:
        """The true horizon in the (undistorted) image; see the module docstring."""
        cam = self.camera
        roll_deg = math.degrees(roll_rad)
        normal_deg = 90.0 - roll_deg
        nx, ny = math.cos(math.radians(normal_deg)), math.sin(math.radians(normal_deg))
        cx, cy = (cam.width - 1) / 2.0, (cam.height - 1) / 2.0
        rho = cam.fx_px * math.tan(max(-1.5, min(1.5, pitch_rad)))  # |pitch| < 86 deg
        rho += nx * (cam.cx_px - cx) + ny * (cam.cy_px - cy)
        return OrientedLine(wrap_deg(normal_deg), rho, cam.width, cam.height)

    def render(self, t_s: float, roll_rad: float, pitch_rad: float,
               rng: np.random.Generator) -> tuple[NDArray[np.uint8], OrientedLine, tuple[str, ...]]:
        """The disturbed BGR frame at this attitude, its true line and the disturbances."""
        cam = self.camera
        pano = self._panorama(t_s)
        truth = self.truth_line(roll_rad, pitch_rad)
        mx, my = self._margin
        out_w, out_h = cam.width + 2 * mx, cam.height + 2 * my
        c = (self._pano_side - 1) / 2.0
        rho = max(-self._rho_max_px, min(self._rho_max_px, truth.rho_px))
        # the frame's centre lies rho on the sky side of the horizon (render_scene's placement)
        centre = (c, c - rho)
        rot = cv2.getRotationMatrix2D(centre, math.degrees(roll_rad), 1.0)
        rot[0, 2] += (out_w - 1) / 2.0 - centre[0]
        rot[1, 2] += (out_h - 1) / 2.0 - centre[1]
        img = np.asarray(cv2.warpAffine(pano, rot, (out_w, out_h), flags=cv2.INTER_LINEAR,
                                        borderMode=cv2.BORDER_REPLICATE), np.uint8)
        if cam.has_distortion:
            img = synth.distort_frame(img, cam, (mx, my))
        img, applied = _disturb(self.disturbance, img, rng, truth)
        return img, truth, applied

    def capture(self, t_s: float, roll_rad: float, pitch_rad: float,
                index: int | None = None) -> CameraResult:
        """Render the frame at the true attitude, detect, convert, count. ``index`` (default:
        the next number) seeds the frame's disturbances."""
        if index is None:
            index = self._index
        self._index = index + 1
        t0, c0 = time.perf_counter(), time.thread_time()
        rng = np.random.default_rng([self.seed, 1, index])
        img, truth, applied = self.render(t_s, roll_rad, pitch_rad, rng)
        est = self._detect(img)
        cost, cpu = time.perf_counter() - t0, time.thread_time() - c0
        failed = not est.found or est.roll_deg is None or est.pitch_deg is None \
            or not est.quality > 0.0
        result = CameraResult(
            index=index, t_s=t_s, handoff_s=t_s + self.latency_s,
            roll_true_rad=roll_rad, pitch_true_rad=pitch_rad, estimate=est, failed=failed,
            roll_rad=math.nan if failed else math.radians(est.roll_deg or 0.0),
            pitch_rad=math.nan if failed else math.radians(est.pitch_deg or 0.0),
            quality=0.0 if failed else min(1.0, est.quality),
            disturbances=applied, cost_s=cost, cpu_s=cpu,
            in_view=truth.border_points() is not None)
        self.stats.add(result)
        return result

    # -- scene ------------------------------------------------------------------------------

    def _lens_margin_px(self) -> tuple[int, int]:
        """Extra pinhole pixels a barrel lens sees beyond the frame (0 without distortion)."""
        cam = self.camera
        if not cam.has_distortion:
            return 0, 0
        w, h = cam.width, cam.height
        tx, ty = np.linspace(0.0, w - 1.0, 33), np.linspace(0.0, h - 1.0, 25)
        border = np.concatenate([np.column_stack([tx, np.zeros_like(tx)]),
                                 np.column_stack([tx, np.full_like(tx, h - 1.0)]),
                                 np.column_stack([np.zeros_like(ty), ty]),
                                 np.column_stack([np.full_like(ty, w - 1.0), ty])])
        und = cam.undistort_points(border)
        mx = math.ceil(max(0.0, -und[:, 0].min(), und[:, 0].max() - (w - 1))) + 2
        my = math.ceil(max(0.0, -und[:, 1].min(), und[:, 1].max() - (h - 1))) + 2
        return int(mx), int(my)

    def _panorama(self, t_s: float) -> NDArray[np.uint8]:
        scene_no = 0 if self.scene == "fixed" else int(max(t_s, 0.0) // self.scene_change_s)
        if self._pano is None or scene_no != self._scene_no:
            rng = np.random.default_rng([self.seed, 0, scene_no])
            side = self._pano_side
            looks = synth.random_spec(rng, clutter=self.clutter)
            # the panorama's focal length is the camera's, so the ground's perspective is too
            hfov = math.degrees(2.0 * math.atan((side / 2.0) / self.camera.fx_px))
            spec = replace(looks, width=side, height=side, roll_deg=0.0, offset_frac=0.0,
                           hfov_deg=hfov)
            t0 = time.perf_counter()
            self._pano, _ = synth.render_scene(spec, rng)
            self._scene_no = scene_no
            log.debug("sim camera: scene %d rendered (%dx%d) in %.0f ms", scene_no, side, side,
                      (time.perf_counter() - t0) * 1e3)
        return self._pano


# ---------------------------------------------------------------------------------------------
# offline: measurements per IMU tick, for companion.evaluation.sitl


class OfflineCameraFeed:
    """Per IMU tick: capture when a frame is due, hand its measurement off ``latency_s`` later.

    Frame times are ``t_ns = round(t_s * 1e9)``, the timebase of ``record_flight``'s IMU
    samples, so the estimator's latency compensation sees the right age.
    """

    def __init__(self, camera: SimCamera, source: str = SOURCE) -> None:
        self.camera = camera
        self.source = source
        self._queue: list[tuple[float, HorizonMeasurement]] = []

    def step(self, t_s: float, roll_rad: float, pitch_rad: float) -> HorizonMeasurement | None:
        """The measurement handed off at ``t_s`` (the newest, if two fall in one tick)."""
        n = self.camera.frame_due(t_s)
        if n is not None:
            r = self.camera.capture(t_s, roll_rad, pitch_rad, n)
            m = r.measurement(int(round(t_s * 1e9)), self.source)
            if m is not None:
                self._queue.append((r.handoff_s, m))
        out = None
        while self._queue and self._queue[0][0] <= t_s + 1e-9:
            out = self._queue.pop(0)[1]
        return out


def horizon_measurements(camera: SimCamera, t_s: NDArray[np.floating],
                         euler_rad: NDArray[np.floating]) -> dict[int, HorizonMeasurement]:
    """Tick -> measurement handed off in it, over a recording's truth (``t_s`` (N,), Euler
    roll, pitch[, yaw] (N, >=2) in rad): the drop-in for ``record_flight``'s truth+noise."""
    feed = OfflineCameraFeed(camera)
    out: dict[int, HorizonMeasurement] = {}
    for k in range(len(t_s)):
        m = feed.step(float(t_s[k]), float(euler_rad[k, 0]), float(euler_rad[k, 1]))
        if m is not None:
            out[k] = m
    return out
