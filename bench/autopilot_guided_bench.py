"""What ArduPlane does when the companion stops sending attitude targets in GUIDED.

Flies `companion sim --autopilot arduplane --autopilot-mode guided` with the control law holding
a 20 deg bank (CTL_MODE 2), switches the law off (CTL_ENABLE 0) after `--hold` simulated seconds
of GUIDED, and prints the true bank (SIMSTATE) each second after the last target, and how long
the autopilot held it. Needs ARDUPILOT_SITL (the ArduPlane SITL binary).

    ARDUPILOT_SITL=PATH python bench/autopilot_guided_bench.py [--speed 5] [--hold 40]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from companion.core.config import Config
from companion.logs.reader import read_log
from companion.sim.autopilot_flight import AutopilotSimOptions, run_with_arduplane
from companion.vehicle import VEHICLE, fill_device_defaults

BANK_DEG = 20.0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speed", type=float, default=5.0)
    ap.add_argument("--hold", type=float, default=40.0, help="simulated s of GUIDED before the stop")
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args()
    if not os.environ.get("ARDUPILOT_SITL"):
        print("autopilot_guided_bench: set ARDUPILOT_SITL to the ArduPlane SITL binary", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        cfg = fill_device_defaults(Config(), VEHICLE)
        cfg.logs.dir = str(Path(tmp) / "flights")
        cfg.params.file = str(Path(tmp) / "params.parm")
        cfg.mavlink.endpoints = []
        cfg.legacy.enabled = False

        def setup(rt: Any) -> None:
            rt.ctx.params.set_many({"CTL_MODE": 2, "CTL_ROLL_SP": BANK_DEG, "CTL_PTCH_SP": 3.0})

            def later() -> None:
                link = rt.manager.find("autopilot")
                while link.counters()["attitude_targets"] < 1:
                    time.sleep(0.05)
                time.sleep(args.hold / args.speed)
                rt.ctx.params.set("CTL_ENABLE", 0)

            threading.Thread(target=later, daemon=True).start()

        summary = run_with_arduplane(cfg, AutopilotSimOptions(speedup=args.speed, mode="guided"),
                                     args.hold + 80.0, handle_signals=False, on_runtime=setup)
        fdir = Path(summary["flight_dir"])
        cmd = read_log(fdir / "autopilot.bin").data(5)
        truth = read_log(fdir / "truth.bin").data(1)
    last = float(cmd["time_s"][-1])
    t = truth["time_s"]
    bank = np.degrees(truth["roll_rad"])
    rows = []
    for dt in range(0, 16):
        m = (t > last + dt) & (t < last + dt + 0.5)
        rows.append((dt, float(np.median(bank[m])) if m.any() else float("nan")))
        print(f"+{dt:>2} s after the last target: true bank {rows[-1][1]:6.1f} deg")
    held = t[(t > last) & (np.abs(bank - BANK_DEG) > 5.0)]
    held_s = float(held[0] - last) if len(held) else None
    print(f"targets sent: {len(cmd)}; the bank left {BANK_DEG:g} +- 5 deg "
          f"{held_s:.1f} s after the last target" if held_s is not None else "never left")
    if args.json:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
        args.json.write_text(json.dumps({
            "command": " ".join(sys.argv), "commit": commit,
            "date": time.strftime("%Y-%m-%d"), "speed": args.speed, "hold_s": args.hold,
            "targets": len(cmd), "held_after_last_target_s": held_s,
            "bank_after_last_target_deg": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
