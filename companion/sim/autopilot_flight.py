"""`companion sim --autopilot arduplane`: the companion beside a real ArduPlane, in SITL.

The autopilot is ArduPilot's own ArduPlane, run as a program (`ArduPlaneSitl`) with its
simulated aircraft; the companion is the real runtime with `[devices.autopilot]` on the
autopilot's first serial port, a pseudo-terminal pair as a TELEM cable would be. A scripted
ground station on the autopilot's second port (`ArduPlaneGround`) does what a pilot does: waits
until the autopilot is ready, uploads a circuit, arms and switches to AUTO (a take-off, then
square laps). With ``--autopilot-mode guided`` it then switches the autopilot to GUIDED, where the
companion's control law flies through it: our estimator's attitude, the law's roll and pitch
targets sent as SET_ATTITUDE_TARGET (`gcs_bridge.autopilot.link`).

What this tests and what it does not (docs/autopilot.md): the link, the streams, the clock
map, the estimator on the autopilot's sensors, the router and the control path, against the
real firmware's MAVLink; not the aircraft's aerodynamics of the thesis (ArduPilot's own plane
model flies here), and not a deterministic flight: the autopilot runs on host time (`--speed`
is its speed-up), so two flights differ in their timing.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

from companion.core.clock import Clock
from companion.core.config import Config
from companion.runtime import Runtime, RuntimeOptions
from companion.sim.ardupilot import ArduPlaneSitl
from companion.sim.ardupilot_mission import ArduPlaneGround, FlightReport, MissionError
from companion.vehicle import apply_device_ports

log = logging.getLogger(__name__)

__all__ = ["AUTOPILOT_MODES", "AutopilotSimOptions", "run_with_arduplane"]

AUTOPILOT_MODES = ("auto", "guided")
GUIDED_AFTER_ALT_M = 60.0
"""With --autopilot-mode guided: the ground switches to GUIDED once the take-off has reached
this height, so the control law takes over a flying aircraft."""


class AutopilotSimOptions:
    """What `companion sim --autopilot` adds to a runtime configuration."""

    def __init__(self, *, binary: str | None = None, defaults: str | None = None,
                 speedup: float = 1.0, mode: str = "auto", instance: int = 0,
                 sysid: int | None = None) -> None:
        if mode not in AUTOPILOT_MODES:
            raise ValueError(f"--autopilot-mode {mode!r}: one of {', '.join(AUTOPILOT_MODES)}")
        self.binary = binary
        self.defaults = defaults
        self.speedup = speedup
        self.mode = mode
        self.instance = instance
        self.sysid = sysid


def run_with_arduplane(cfg: Config, sim: AutopilotSimOptions, duration_s: float, *,
                       handle_signals: bool = True,
                       on_runtime: Callable[[Runtime], None] | None = None) -> dict[str, Any]:
    """Fly the companion beside ArduPlane SITL for `duration_s` simulated seconds; the runtime's
    summary with the autopilot's report (`summary["autopilot_sitl"]`)."""
    with ArduPlaneSitl(sim.binary, speedup=sim.speedup, defaults=sim.defaults,
                       instance=sim.instance, sysid=sim.sysid) as sitl:
        apply_device_ports(cfg, {"autopilot": sitl.companion_url})
        rt = Runtime(cfg, RuntimeOptions(
            clock=Clock(sim.speedup),
            extra_run_info={"simulation": {"autopilot": "arduplane", "speedup": sim.speedup,
                                           "mode": sim.mode}}))
        if on_runtime is not None:
            on_runtime(rt)
        ground_errors: list[str] = []
        report = FlightReport()
        stop_ground = threading.Event()

        def pilot() -> None:
            try:
                with ArduPlaneGround(sitl.ground_url, speedup=sim.speedup,
                                     target_system=sitl.sysid) as ground:
                    ground.start_mission()
                    if sim.mode == "guided":
                        ground.fly(duration_s, lambda r: (stop_ground.is_set()
                                                          or r.relative_alt_m > GUIDED_AFTER_ALT_M))
                        ground.set_mode("GUIDED")
                    ground.fly(duration_s, lambda r: stop_ground.is_set())
                    report.__dict__.update(ground.report.__dict__)
            except (MissionError, OSError) as exc:
                ground_errors.append(str(exc))
                log.error("the scripted ground station stopped: %s", exc)

        ground_thread = threading.Thread(target=pilot, name="arduplane-ground", daemon=True)
        ground_thread.start()
        t0 = time.monotonic()
        try:
            reason = rt.run(duration_s, handle_signals=handle_signals)
        finally:
            stop_ground.set()
            ground_thread.join(10.0)
        summary = rt.summary()
        summary["stop_reason"] = reason
        summary["host_seconds"] = round(time.monotonic() - t0, 2)
        summary["autopilot_sitl"] = {**asdict(report), "errors": ground_errors,
                                     "speedup": sim.speedup, "mode": sim.mode}
        return summary
