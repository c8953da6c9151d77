"""The world process (`python -m companion.sim.world_process`): the entry point `companion sim`
starts for the simulated world of a real-time or `--speed` flight.

Its own module because it is the world's process, not the world: its command line (the
options `companion.sim.runner.WorldProcess` passes, the world faults among them from the
catalogue `companion.sim.faults`), the handshake with the runner over stdin and stdout
(``READY {devices, home, params}``, then ``GO {...}`` once the runtime has opened its ports,
``DEST {...}`` when a rebooted runtime bound a new legacy port, ``STATS {...}`` at the end) and
its signals. The world itself (`companion.sim.world.World`) knows nothing of them.
"""

from __future__ import annotations

import argparse
import json
import logging
import select
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from companion.sim.faults import parse_fault, parse_vanish, world_faults
from companion.sim.flight import FlightModelError
from companion.sim.plugins import simulated_devices
from companion.sim.profiles import GPS_PROFILES, IMU_PROFILES, TURBULENCE
from companion.sim.world import HORIZON_CAMERA_CHOICES, World, WorldOptions

__all__ = ["GO_TIMEOUT_S", "main"]

GO_TIMEOUT_S = 120.0
"""How long the world waits for the runtime's GO after READY."""


def _follow_stdin(world: World) -> None:
    """After GO, the runner may name a new camera destination (`DEST {"horizon_dest": ...}`)
    when the runtime reboots; anything else, or the pipe closing, is ignored."""
    for line in sys.stdin:
        word, _, extra = line.strip().partition(" ")
        if word != "DEST":
            continue
        try:
            world.retarget_camera(str(json.loads(extra)["horizon_dest"]))
        except (ValueError, KeyError, TypeError) as exc:
            print(f"companion.sim.world_process: bad DEST line {line.strip()!r}: {exc}", file=sys.stderr)



def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="companion.sim.world_process", description=__doc__)
    ap.add_argument("--scenario", default="mixed")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--aircraft", default="c172p")
    ap.add_argument("--wind", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("N", "E", "D"))
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--epoch", type=int, nargs=2, metavar=("MONO_NS", "REAL_NS"))
    ap.add_argument("--device-dir", type=Path, required=True)
    ap.add_argument("--flight-dir", type=Path)
    ap.add_argument("--duration", type=float, default=0.0)
    ap.add_argument("--gps-latency", type=float)
    ap.add_argument("--imu-seed", type=int)
    ap.add_argument("--imu-profile", choices=list(IMU_PROFILES))
    ap.add_argument("--gps-profile", choices=list(GPS_PROFILES))
    ap.add_argument("--turbulence", choices=list(TURBULENCE))
    ap.add_argument("--gps-ashtech", action="store_true")
    for kind in world_faults():
        ap.add_argument(kind.option, action="append", default=[], metavar=kind.syntax,
                        help=kind.help)
    ap.add_argument("--auto-switch", type=float, default=20.0)
    ap.add_argument("--no-noise", action="store_true")
    ap.add_argument("--no-level-cal", action="store_true")
    ap.add_argument("--horizon-camera", default="off", choices=HORIZON_CAMERA_CHOICES)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="sim: %(levelname)s %(message)s")
    try:
        faults = dict(parse_fault(f) for f in args.fault)
        vanish = [parse_vanish(v) for v in args.vanish]
    except ValueError as exc:
        print(f"companion.sim.world_process: {exc}", file=sys.stderr)
        return 2
    opts = WorldOptions(
        scenario=args.scenario, seed=args.seed, aircraft=args.aircraft,
        wind_ned_m_s=tuple(args.wind), scale=args.scale,
        epoch=tuple(args.epoch) if args.epoch else None, device_dir=args.device_dir,
        flight_dir=args.flight_dir, duration_s=args.duration, gps_latency_s=args.gps_latency,
        imu_seed=args.imu_seed,
        gps_ashtech=args.gps_ashtech, faults=faults, vanish=vanish, imu_noise=not args.no_noise,
        imu_profile=args.imu_profile, gps_profile=args.gps_profile, turbulence=args.turbulence,
        auto_switch_s=args.auto_switch, horizon_camera=args.horizon_camera,
        level_calibration=not args.no_level_cal, extra_devices=simulated_devices())
    try:
        world = World(opts)
    except (FlightModelError, ValueError) as exc:
        print(f"companion.sim.world_process: cannot start: {exc}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, lambda *_: world.stop())
    signal.signal(signal.SIGINT, lambda *_: world.stop())
    frame = world.model.frame
    ready: dict[str, Any] = {d: str(opts.device_dir / d) for d in world.device_names}
    ready["home"] = [frame.lat0_deg, frame.lon0_deg, frame.alt0_m]
    ready["params"] = world.runtime_params()
    print("READY " + json.dumps(ready), flush=True)
    # Fly only once the runtime has opened its ports: until then nobody would read the devices.
    # The GO line may carry what only the started runtime knows: `GO {"horizon_dest": ...}`.
    ready_to_fly, _, _ = select.select([sys.stdin], [], [], GO_TIMEOUT_S)
    line = sys.stdin.readline().strip() if ready_to_fly else ""
    word, _, extra = line.partition(" ")
    if word != "GO":
        for pty in world.ptys.values():
            pty.close()
        print("companion.sim.world_process: the runtime never said GO", file=sys.stderr)
        return 1
    try:
        go = json.loads(extra) if extra else {}
        if opts.horizon_camera != "off":
            world.attach_camera(str(go["horizon_dest"]), vehicle_id=int(go.get("vehicle_id", 1)))
    except (ValueError, KeyError, TypeError) as exc:
        for pty in world.ptys.values():
            pty.close()
        print(f"companion.sim.world_process: bad GO line {line!r}: {exc}", file=sys.stderr)
        return 1
    if world.camera is not None:
        threading.Thread(target=_follow_stdin, args=(world,), name="world-stdin",
                         daemon=True).start()
    stats = world.run()
    try:
        print("STATS " + json.dumps(stats), flush=True)
    except BrokenPipeError:  # the runtime is gone (killed): nobody to report to
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
