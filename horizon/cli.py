"""``companion horizon detect | stream | synth``: the command-line face of the horizon package.

The main ``companion`` CLI creates the ``horizon`` group and calls :func:`add_commands` with its
sub-parsers; each handler returns the exit code: 0 success, 1 some inputs or frames could not be
used, 2 bad arguments or unusable inputs.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from horizon.detector import DEFAULT_METHOD, create_detector, method_names

# The main CLI imports this module for every `companion ...` command: the outputs and frame
# sources (and numpy) are imported by the commands that use them.
if TYPE_CHECKING:
    import numpy as np

    from horizon.camera import CameraModel
    from horizon.estimate import HorizonEstimate
    from horizon.sources import Frame

log = logging.getLogger(__name__)

__all__ = ["add_commands"]


def add_commands(sub: argparse._SubParsersAction,  # type: ignore[type-arg]
                 rerun_frames: Callable[..., Any] | None = None) -> None:
    """Add ``detect``, ``stream`` and ``synth`` to the ``companion horizon`` group.

    `rerun_frames` makes the viewer for ``stream --rerun``: a callable
    ``(spawn=bool, save_path=Path | None)`` returning an object called as
    ``viewer(image, estimate, t_ns)`` with a ``close()``. The companion's CLI passes its live-view
    adapter; without one, ``--rerun`` is refused with a message (this package stays free of the
    companion runtime)."""
    det = sub.add_parser(
        "detect",
        help="find the horizon in images, folders, videos or a camera; write CSV and overlays",
        description="Find the horizon in every frame of the inputs. CSV goes to --csv, or to "
        "standard output when --csv is not given.",
    )
    det.add_argument("inputs", nargs="+", metavar="INPUT",
                     help="image file, folder of images, video file, or camera:N")
    _add_common(det)
    det.add_argument("--csv", metavar="OUT", help="CSV file to write ('-' for standard output)")
    det.add_argument("--overlay", metavar="DIR", help="write each frame with the horizon drawn in, as PNG")
    det.add_argument("--overlay-video", metavar="FILE", help="write the overlay frames as one video")
    det.add_argument("--track", choices=("auto", "on", "off"), default="auto",
                     help="temporal tracking between frames (auto: on for video and cameras)")
    det.set_defaults(func=_cmd_detect)

    st = sub.add_parser(
        "stream",
        help="run on a video or camera and send each estimate to the aircraft",
        description="Detect the horizon on a video or camera and send every estimate as the "
        "legacy HORIZON_ATTITUDE command and/or as MAVLink (ATTITUDE from component 100 plus "
        "NAMED_VALUE_FLOAT HZN_QUAL). Pitch needs the camera: give --camera or --hfov-deg.",
    )
    st.add_argument("input", metavar="INPUT", help="video file or camera:N")
    _add_common(st)
    st.add_argument("--legacy", action="append", default=[], metavar="HOST[:PORT]",
                    help="send HORIZON_ATTITUDE here (port 5500 by default); repeatable")
    st.add_argument("--vehicle-id", type=int, default=1, help="legacy vehicle id (1..255)")
    st.add_argument("--mavlink", action="append", default=[], metavar="URL",
                    help="pymavlink connection string, e.g. udpout:127.0.0.1:14550; repeatable")
    st.add_argument("--system-id", type=int, default=1, help="MAVLink system id of the aircraft")
    st.add_argument("--rate-hz", type=float, default=None,
                    help="play a video file at this frame rate (default: as fast as possible)")
    st.add_argument("--no-track", action="store_true", help="single-frame detection only")
    st.add_argument("--csv", metavar="OUT", help="also log every estimate to this CSV")
    st.add_argument("--rerun", action="store_true",
                    help="show the frames and the detected horizon in a spawned rerun viewer")
    st.add_argument("--rerun-save", metavar="PATH",
                    help="write the frames and the detected horizon to a rerun .rrd file")
    st.set_defaults(func=_cmd_stream, rerun_frames=rerun_frames)

    sy = sub.add_parser(
        "synth",
        help="write synthetic frames at known attitudes, with gt.csv, for tests and tuning",
    )
    sy.add_argument("outdir", metavar="DIR")
    sy.add_argument("--count", type=int, default=20)
    sy.add_argument("--width", type=int, default=320)
    sy.add_argument("--height", type=int, default=240)
    sy.add_argument("--disturbance", default="clean", help="clean, noise, stripes, black-stripes, "
                    "exposure, colour or glare")
    sy.add_argument("--clutter", action="store_true", help="add roads and buildings")
    sy.add_argument("--seed", type=int, default=0)
    sy.set_defaults(func=_cmd_synth)


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--method", default=DEFAULT_METHOD, choices=method_names(),
                   help=f"detector (default {DEFAULT_METHOD}; 'baseline' is the thesis's 2003 pipeline)")
    p.add_argument("--camera", metavar="FILE",
                   help="camera intrinsics and radial distortion (JSON or TOML), for pitch and "
                   "distortion correction")
    p.add_argument("--hfov-deg", type=float, default=None,
                   help="horizontal field of view, when no camera file exists (no distortion)")
    p.add_argument("--max-frames", type=int, default=None, help="stop after this many frames")


def _camera(args: argparse.Namespace, frame_size: tuple[int, int] | None) -> CameraModel | None:
    from horizon.camera import CameraModel

    if args.camera:
        return CameraModel.load(args.camera)
    if args.hfov_deg is not None:
        if frame_size is None:
            return None
        return CameraModel.from_hfov(frame_size[0], frame_size[1], args.hfov_deg)
    return None


class _Estimator:
    """Detector (with or without tracking) built lazily, once the first frame's size is known
    (a field of view alone gives intrinsics only for a frame size)."""

    def __init__(self, args: argparse.Namespace, track: bool) -> None:
        self.args = args
        self.track = track
        self.camera: CameraModel | None = None
        self._fn: object = None

    def __call__(self, image: np.ndarray) -> HorizonEstimate:
        if self._fn is None:
            h, w = image.shape[:2]
            self.camera = _camera(self.args, (w, h))
            detector = create_detector(self.args.method, self.camera)
            if self.track and detector.name == "robust":
                from horizon.robust import RobustDetector
                from horizon.tracking import HorizonTracker

                assert isinstance(detector, RobustDetector)
                self._fn = HorizonTracker(detector).update
            else:
                self._fn = detector.detect
        return self._fn(image)  # type: ignore[operator, no-any-return]

    def reset(self) -> None:
        """Forget the previous video (its tracking state and frame size)."""
        self._fn = None


def _host_port(text: str, default_port: int) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep:
        return text, default_port
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"{text}: expected HOST or HOST:PORT with a port in 1..65535")
    return host, int(port)


def _fail(message: str) -> int:
    print(f"companion horizon: {message}", file=sys.stderr)
    return 2


def _cmd_detect(args: argparse.Namespace) -> int:
    from horizon.camera import CameraError, CameraModel
    from horizon.output import CsvSink, OutputError, OverlayFrames, OverlayVideo, draw_overlay
    from horizon.sources import FrameSourceError, iter_frames, parse_input

    try:
        specs = [parse_input(t) for t in args.inputs]
        if args.camera:
            CameraModel.load(args.camera)  # fail before any frame is read
    except (FrameSourceError, CameraError) as exc:
        return _fail(str(exc))
    if args.max_frames is not None and args.max_frames <= 0:
        return _fail("--max-frames must be positive")
    track = args.track == "on" or (
        args.track == "auto" and any(s.kind in ("video", "camera") for s in specs)
    )
    errors: list[str] = []

    def on_error(message: str) -> None:
        errors.append(message)
        print(f"companion horizon: {message}", file=sys.stderr)

    try:
        sink = CsvSink(sys.stdout if args.csv in (None, "-") else args.csv)
        frames_out = OverlayFrames(args.overlay) if args.overlay else None
        video_out = OverlayVideo(args.overlay_video) if args.overlay_video else None
    except OutputError as exc:
        return _fail(str(exc))
    estimator = _Estimator(args, track)
    last_source = None
    n = found = 0
    try:
        for frame in iter_frames(args.inputs, on_error, args.max_frames):
            if track and frame.source != last_source and last_source is not None:
                estimator.reset()  # a new video: no memory of the last one
            last_source = frame.source
            est = estimator(frame.image)
            sink.write(frame.label, est)
            n += 1
            found += int(est.found)
            if frames_out is not None or video_out is not None:
                over = draw_overlay(frame.image, est, estimator.camera)
                if frames_out is not None:
                    frames_out.write(frame.label, frame.index, over)
                if video_out is not None:
                    video_out.write(over)
    except (OutputError, CameraError) as exc:
        return _fail(str(exc))
    except KeyboardInterrupt:
        print("companion horizon: interrupted", file=sys.stderr)
    finally:
        sink.close()
        if video_out is not None:
            video_out.close()
    print(f"companion horizon: {n} frames, horizon found in {found}", file=sys.stderr)
    return 1 if errors else 0


def _cmd_stream(args: argparse.Namespace) -> int:
    import threading

    from horizon.camera import CameraError, CameraModel
    from horizon.output import CsvSink, OutputError
    from horizon.sources import FrameSourceError, iter_frames, parse_input
    from horizon.stream import LegacyHorizonSender, MavlinkHorizonSender, Sender, run_stream

    if not args.legacy and not args.mavlink:
        return _fail("nothing to send to: give --legacy HOST[:PORT] and/or --mavlink URL")
    if not args.camera and args.hfov_deg is None:
        return _fail("pitch needs the camera: give --camera FILE or --hfov-deg DEG")
    try:
        spec = parse_input(args.input)
        if spec.kind in ("image", "folder"):
            return _fail(f"{args.input}: stream takes a video file or camera:N, not images")
        if args.camera:
            CameraModel.load(args.camera)
    except (FrameSourceError, CameraError) as exc:
        return _fail(str(exc))
    if args.rate_hz is not None and not 0 < args.rate_hz <= 1000:
        return _fail("--rate-hz must be in (0, 1000]")
    if args.max_frames is not None and args.max_frames <= 0:
        return _fail("--max-frames must be positive")

    senders: list[Sender] = []
    closers = []
    try:
        for target in args.legacy:
            host, port = _host_port(target, 5500)
            legacy = LegacyHorizonSender(host, port, args.vehicle_id)
            senders.append(legacy)
            closers.append(legacy.close)
        for url in args.mavlink:
            mav = MavlinkHorizonSender(url, system_id=args.system_id)
            senders.append(mav)
            closers.append(mav.close)
    except ValueError as exc:
        for close in closers:
            close()
        return _fail(str(exc))

    errors: list[str] = []
    sink = None
    try:
        if args.csv:
            sink = CsvSink(args.csv)
    except OutputError as exc:
        for close in closers:
            close()
        return _fail(str(exc))

    viewer = None
    if args.rerun or args.rerun_save:
        make_viewer = getattr(args, "rerun_frames", None)
        if make_viewer is None:
            for close in closers:
                close()
            return _fail("--rerun/--rerun-save: no rerun viewer adapter (run it as `companion "
                         "horizon stream`)")
        try:
            viewer = make_viewer(spawn=args.rerun,
                                 save_path=Path(args.rerun_save) if args.rerun_save else None)
        except Exception as exc:  # rerun raises several kinds for a bad path or no viewer
            for close in closers:
                close()
            return _fail(f"rerun: {exc}")
        closers.append(viewer.close)

    def on_estimate(frame: Frame, est: HorizonEstimate) -> None:
        if sink is not None:
            sink.write(frame.label, est)
        if viewer is not None:
            viewer(frame.image, est, frame.time_ns)

    def on_error(message: str) -> None:
        errors.append(message)
        print(f"companion horizon: {message}", file=sys.stderr)

    stop = threading.Event()
    estimator = _Estimator(args, track=not args.no_track)
    try:
        frames: Iterator[Frame] = iter_frames([args.input], on_error, args.max_frames)
        stats = run_stream(frames, estimator, senders, on_estimate, stop, args.rate_hz)
    except KeyboardInterrupt:
        stop.set()
        print("companion horizon: interrupted", file=sys.stderr)
        return 0
    finally:
        for close in closers:
            close()
        if sink is not None:
            sink.close()
    print(
        f"companion horizon: {stats.frames} frames, horizon found in {stats.found}, "
        f"{stats.send_errors} send errors",
        file=sys.stderr,
    )
    return 1 if errors or stats.send_errors else 0


def _cmd_synth(args: argparse.Namespace) -> int:
    import csv

    import numpy as np

    from horizon.synth import DISTURBANCES, apply_disturbance, random_spec, render_scene

    if args.disturbance not in DISTURBANCES:
        return _fail(f"unknown disturbance {args.disturbance!r}; choose from {', '.join(DISTURBANCES)}")
    if not 0 < args.count <= 100_000:
        return _fail("--count must be in 1..100000")
    if not (16 <= args.width <= 4096 and 16 <= args.height <= 4096):
        return _fail("--width and --height must be in 16..4096")
    out = Path(args.outdir)
    try:
        (out / "images").mkdir(parents=True, exist_ok=True)
        gt_file = (out / "gt.csv").open("w", newline="", encoding="utf-8")
    except OSError as exc:
        return _fail(f"{out}: cannot write: {exc.strerror or exc}")
    import cv2

    rng = np.random.default_rng(args.seed)
    with gt_file:
        w = csv.writer(gt_file, lineterminator="\n")
        w.writerow(["image", "width", "height", "x1", "y1", "x2", "y2", "roll_deg", "offset_frac", "clip"])
        for i in range(args.count):
            spec = random_spec(rng, args.width, args.height, clutter=args.clutter)
            img, truth = render_scene(spec, rng)
            img = apply_disturbance(args.disturbance, img, rng, truth)
            name = f"images/synth_{i:05d}.png"
            if not cv2.imwrite(str(out / name), img):
                return _fail(f"{out / name}: cannot write image")
            ends = truth.border_points()
            if ends is None:
                continue
            (x1, y1), (x2, y2) = ends
            w.writerow([name, args.width, args.height, f"{x1:.6f}", f"{y1:.6f}", f"{x2:.6f}",
                        f"{y2:.6f}", f"{truth.roll_deg:.6f}", f"{truth.offset_frac:.6f}",
                        args.disturbance])
    print(f"companion horizon: wrote {args.count} frames and gt.csv to {out}", file=sys.stderr)
    return 0
