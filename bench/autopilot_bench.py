"""Beside a flight controller: our estimator against ArduPilot's EKF3, and the runtime's CPU,
in ArduPlane's own simulator (SITL), not our JSBSim world.

    ARDUPILOT_SITL=PATH .venv/bin/python bench/autopilot_bench.py           # 3 flights a setting
    ARDUPILOT_SITL=PATH .venv/bin/python bench/autopilot_bench.py --quick   # 1 flight a setting
    ... --json figures.json --md figures.md

Every flight is a real ``companion sim --autopilot arduplane --speed 5`` process of ~120
simulated seconds in AUTO (the scripted ground arms once ArduPilot is ready, about 20 s in,
then take-off and the square circuit: docs/autopilot.md), with ``--mavlink none --no-legacy``.
The SITL binary comes from ``ARDUPILOT_SITL`` (a missing one ends the bench with one line).

1. Estimation. For each flight, ours (``estimator.bin``) and ArduPilot's (``autopilot.bin``:
   ATTITUDE and GLOBAL_POSITION_INT, EKF3 with the defaults, ``AHRS_EKF_TYPE 3``) against the
   simulator's truth (SIMSTATE, ``truth.bin``): inclination RMSE (the angle between the true
   and the estimated vertical), heading RMSE (wrapped) and horizontal position error. The
   estimator's NED origin is set to SITL's home (``vehicle.home``), so its north/east and the
   truth's latitude/longitude share one frame. SIMSTATE carries no velocity: our velocity is
   compared with ArduPilot's (a reference, not the truth). Two sensor settings: SITL's
   defaults, and a consumer-MEMS level raised through ArduPilot's ``SIM_*`` parameters
   (`MEMS_OVERRIDES`, written after ``plane.parm`` into one defaults file).
2. Runtime CPU. The ``companion sim`` process's CPU over each flight's steady part (from a
   quarter in to the last sample before it exits), per simulated second, with the link at the
   rates it asks for; the baseline, flown in the same run between the same flights, is the
   same command with the estimator and the control law off (a two-line driver sets
   ``RuntimeOptions(estimator=False, control=False)``: the command line has no switch for it).
   The process also holds the test harness (the pseudo-terminal cable's pump and the scripted
   ground station): the per-thread table shows what is the runtime's.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.result import Result  # noqa: E402
from companion.core.geo import NedFrame  # noqa: E402
from companion.estimation.params import estimator_param_defaults  # noqa: E402
from companion.estimation.quat import (  # noqa: E402
    heading_error_rad,
    inclination_error_rad,
    quat_from_euler,
)
from companion.evaluation.sitl_estimator import ESTIMATOR_PARAM_PREFIX  # noqa: E402
from companion.logs.reader import read_log  # noqa: E402
from companion.sim.ardupilot import SitlNotFound, find_binary, find_defaults  # noqa: E402

SPEED = 5.0
DURATION_S = 120.0
SITL_HOME = (-35.363261, 149.165230, 584.0)
"""ArduPilot SITL's default home (CMAC), where the aircraft starts: the estimator's origin."""
WARMUP_S = 5.0
"""Seconds after both filters have a solution that are not scored."""
MOVING_M_S = 5.0
"""A GPS fix is checked for its dating only while the true ground speed exceeds this."""
TURN_BANK_RAD = 20.0 * math.pi / 180.0
"""The 'turns' window: samples where the true bank exceeds this."""
MAX_GAP_S = 0.25
"""An estimate is interpolated only between two records at most this far apart."""
SAMPLE_S = 0.25

DEG = math.pi / 180.0
# A consumer-MEMS level (our `consumer` IMU profile, MPU-6000 class, and the u-blox M8 class:
# companion/sim/profiles.py) in the SIM_* parameters this ArduPlane has (read from the running
# SITL: SIM_GYRn_RND/BIAS/SCALE, SIM_ACCn_BIAS, SIM_GPS1_VERR/NOISE). Both simulated IMUs get
# their own errors, so EKF3 cannot escape to a clean second IMU.
MEMS_OVERRIDES: dict[str, float] = {
    # gyro white noise: SITL adds uniform(+-RND deg/s) x throttle to each of the 8 samples it
    # averages per 1 kHz gyro sample once the throttle is above SIM_INS_THR_MIN; at ~50 %
    # throttle 1.0 gives 0.5/sqrt(3)/sqrt(8) = 0.10 deg/s per 1 kHz sample, about
    # 0.005 deg/s/sqrt(Hz) (the MPU-6000's rate noise density)
    "SIM_GYR1_RND": 1.0, "SIM_GYR2_RND": 1.0,
    # gyro bias left after the power-up calibration: ~0.2 deg/s per axis (profile's sigma),
    # in rad/s; ArduPlane's plane.parm has INS_GYR_CAL 0 (no calibration at boot), so neither
    # filter is handed it
    "SIM_GYR1_BIAS_X": 0.20 * DEG, "SIM_GYR1_BIAS_Y": -0.15 * DEG, "SIM_GYR1_BIAS_Z": 0.10 * DEG,
    "SIM_GYR2_BIAS_X": -0.15 * DEG, "SIM_GYR2_BIAS_Y": 0.20 * DEG, "SIM_GYR2_BIAS_Z": -0.10 * DEG,
    # gyro scale-factor error, percent (profile: 1 % sigma of the +-3 % tolerance)
    "SIM_GYR1_SCALE_X": 1.0, "SIM_GYR1_SCALE_Y": -0.8, "SIM_GYR1_SCALE_Z": 0.6,
    "SIM_GYR2_SCALE_X": -0.7, "SIM_GYR2_SCALE_Y": 0.9, "SIM_GYR2_SCALE_Z": -1.0,
    # accelerometer bias left after the six-position calibration: ~5 mg (profile's sigma)
    "SIM_ACC1_BIAS_X": 0.05, "SIM_ACC1_BIAS_Y": -0.04, "SIM_ACC1_BIAS_Z": 0.05,
    "SIM_ACC2_BIAS_X": -0.04, "SIM_ACC2_BIAS_Y": 0.05, "SIM_ACC2_BIAS_Z": -0.05,
    # GPS velocity error: uniform(+-VERR) per axis per fix (std 0.06 / 0.09 m/s; M8: 0.05)
    "SIM_GPS1_VERR_X": 0.1, "SIM_GPS1_VERR_Y": 0.1, "SIM_GPS1_VERR_Z": 0.15,
    # GPS altitude error: SITL's is a slow sine of this amplitude (m)
    "SIM_GPS1_NOISE": 2.0,
}
NOT_RAISED = (
    "accelerometer white noise (this SITL adds SIM_ACCn_RND only through a vibration model, "
    "SIM_VIB_FREQ / SIM_VIB_MOT_MAX, which would also replace the gyro's white noise by a tone: "
    "it stays at SITL's 0.01 m/s2 uniform)",
    "GPS horizontal position noise (this SITL has no random horizontal error: only a constant "
    "glitch offset, SIM_GPS1_GLTCH; the fix is the true position 100 ms late, SIM_GPS1_LAG_MS)",
)
SETTINGS = ("defaults", "consumer-mems")
HARNESS = "unnamed (harness: cable pump, ground station; libraries)"
"""Threads without an OS name: the test harness's Python threads (and idle library threads)."""

BASELINE_DRIVER = """\
import functools, sys
import companion.sim.autopilot_flight as flight
from companion.cli import main
flight.RuntimeOptions = functools.partial(flight.RuntimeOptions, estimator=False, control=False)
sys.exit(main(sys.argv[1:]))
"""
"""``companion sim`` with the estimator and the control law off (the CPU baseline)."""


# ------------------------------------------------------------------------------ flying


def defaults_file(tmp: Path, setting: str) -> Path | None:
    """None for SITL's defaults; for the MEMS setting plane.parm (read from beside the binary
    now) with `MEMS_OVERRIDES` after it, in one file (ArduPlaneSitl takes one path)."""
    if setting == "defaults":
        return None
    base = find_defaults(find_binary()).read_text(encoding="utf-8")
    lines = [base.rstrip("\n"), "# autopilot_bench.py: a consumer-MEMS level"]
    lines += [f"{name} {value:.6g}" for name, value in MEMS_OVERRIDES.items()]
    path = tmp / f"{setting}.parm"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def thread_cpu_s(pid: int) -> dict[int, tuple[str, float]]:
    """CPU seconds of every thread of `pid` by thread id, with its OS name (the runtime's
    managed threads name themselves; Python threads of the harness carry the process's name)."""
    tick = float(os.sysconf("SC_CLK_TCK"))
    out: dict[int, tuple[str, float]] = {}
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            comm = (task / "comm").read_text().strip()
            fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        tid = int(task.name)
        name = "main thread (manager)" if tid == pid else comm
        out[tid] = (name, (int(fields[11]) + int(fields[12])) / tick)
    return out


def fly(tmp: Path, label: str, setting: str, duration_s: float, *,
        baseline: bool = False) -> dict[str, Any]:
    """One flight; its summary, CPU figures and flight directory."""
    cmd_tail = ["sim", "--autopilot", "arduplane", "--speed", f"{SPEED:g}",
                "--duration", f"{duration_s:g}", "--autopilot-mode", "auto",
                "--mavlink", "none", "--no-legacy", "--json",
                "--log-dir", str(tmp / label), "--params-file", str(tmp / f"{label}.parm"),
                "--set", "vehicle.home=" + ",".join(repr(v) for v in SITL_HOME)]
    parm = defaults_file(tmp, setting)
    if parm is not None:
        cmd_tail += ["--autopilot-defaults", str(parm)]
    head = ([sys.executable, "-c", BASELINE_DRIVER] if baseline
            else [sys.executable, "-m", "companion"])
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        p for p in (str(root), os.environ.get("PYTHONPATH", "")) if p)}
    proc = subprocess.Popen(head + cmd_tail, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=root, env=env)
    ps = psutil.Process(proc.pid)
    samples: list[tuple[float, float, float]] = []  # host s, companion CPU s, autopilot CPU s
    threads: list[dict[int, tuple[str, float]]] = []
    t0 = time.monotonic()
    while proc.poll() is None:
        try:
            own = sum(ps.cpu_times()[:2])
            kids = sum(sum(k.cpu_times()[:2]) for k in ps.children(recursive=True))
            snap = thread_cpu_s(proc.pid)
            samples.append((time.monotonic() - t0, own, kids))
            threads.append(snap)
        except (psutil.Error, OSError):
            pass
        time.sleep(SAMPLE_S)
    out, err = proc.communicate()
    if proc.returncode != 0 or not out.strip():
        raise SystemExit(f"{label}: exit {proc.returncode}: {err.strip()[-1500:]}")
    summary = json.loads(out)
    i_first = next(i for i, s in enumerate(samples) if s[0] >= samples[-1][0] * 0.25)
    i_last = max(i_first + 1, len(samples) - 2)
    first, last = samples[i_first], samples[min(i_last, len(samples) - 1)]
    span = last[0] - first[0]
    per_thread: dict[str, float] = {}
    for tid, (name, cpu) in threads[min(i_last, len(samples) - 1)].items():
        before = threads[i_first].get(tid, (name, 0.0))[1]
        key = name if (name.startswith("main thread") or name not in ("python", "python3",
                                                                       "python3.11")) \
            else HARNESS
        per_thread[key] = per_thread.get(key, 0.0) + (cpu - before)
    rates = {t["name"]: t["rate_hz"] for t in summary["threads"]}
    link = next(t for t in summary["threads"] if t["name"] == "autopilot")
    report = summary["autopilot_sitl"]
    return {
        "label": label, "setting": setting, "baseline": baseline,
        "command": " ".join(["python", "-m", "companion"] + cmd_tail).replace(str(tmp), "$TMP"),
        "flight_dir": summary["flight_dir"],
        "host_s": round(samples[-1][0], 2),
        "autopilot_sim_s": report["sim_s"],
        "autopilot_speed": round(report["sim_s"] / max(summary["host_seconds"], 1e-9), 2),
        "ground_errors": report["errors"], "max_relative_alt_m": report["max_relative_alt_m"],
        "ekf3_active": any("EKF3 active" in s for s in report["statustexts"]),
        "restarts": sum(t["restarts"] for t in summary["threads"]),
        "rates_hz": rates, "imu_samples": link["counters"]["imu_samples"],
        "gps_fixes": link["counters"]["gps_fixes"],
        "estimator_counters": next((t["counters"] for t in summary["threads"]
                                    if t["name"] == "estimator"), None),
        "cpu": {
            "span_host_s": round(span, 2),
            "companion_pct_core": 100 * (last[1] - first[1]) / span,
            "companion_ms_per_sim_s": 1000 * (last[1] - first[1]) / (span * SPEED),
            "runtime_ms_per_sim_s": 1000 * sum(v for k, v in per_thread.items()
                                               if k != HARNESS) / (span * SPEED),
            "autopilot_pct_core": 100 * (last[2] - first[2]) / span,
            "threads_ms_per_sim_s": {k: 1000 * v / (span * SPEED)
                                     for k, v in sorted(per_thread.items(), key=lambda kv: -kv[1])},
        },
    }


# ------------------------------------------------------------------------------ scoring


def _continuous(q: np.ndarray) -> np.ndarray:
    """Quaternions with the sign of each chosen next to the one before (for interpolation)."""
    q = q.copy()
    flips = np.sum(q[1:] * q[:-1], axis=1) < 0
    sign = np.cumprod(np.where(flips, -1.0, 1.0))
    q[1:] *= sign[:, None]
    return q


def _interp_at(t_src: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices, weights and validity for linear interpolation of a record series at `t`."""
    j = np.clip(np.searchsorted(t_src, t), 1, len(t_src) - 1)
    t0, t1 = t_src[j - 1], t_src[j]
    w = np.where(t1 > t0, (t - t0) / np.where(t1 > t0, t1 - t0, 1.0), 0.0)
    ok = (t >= t_src[0]) & (t <= t_src[-1]) & (t1 - t0 <= MAX_GAP_S)
    return j, np.clip(w, 0.0, 1.0), ok


def interp_quat(t_src: np.ndarray, q_src: np.ndarray, t: np.ndarray) -> tuple[np.ndarray,
                                                                                np.ndarray]:
    q = _continuous(q_src)
    j, w, ok = _interp_at(t_src, t)
    out = (1 - w)[:, None] * q[j - 1] + w[:, None] * q[j]
    return out / np.linalg.norm(out, axis=1)[:, None], ok


def interp_cols(t_src: np.ndarray, cols: np.ndarray, t: np.ndarray) -> tuple[np.ndarray,
                                                                               np.ndarray]:
    j, w, ok = _interp_at(t_src, t)
    return (1 - w)[:, None] * cols[j - 1] + w[:, None] * cols[j], ok


def _stats(err: np.ndarray) -> dict[str, float]:
    err = np.abs(err[np.isfinite(err)])
    if len(err) == 0:
        return {"rmse": math.nan, "p95": math.nan, "max": math.nan, "n": 0}
    return {"rmse": float(np.sqrt(np.mean(err ** 2))), "p95": float(np.percentile(err, 95)),
            "max": float(err.max()), "n": int(len(err))}


def _ne(frame: NedFrame, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
    return np.array([frame.to_ned(a, b, frame.alt0_m)[:2] for a, b in zip(lat, lon, strict=True)])


def gps_dating_s(t: np.ndarray, ne_true: np.ndarray, speed: np.ndarray, t_fix: np.ndarray,
                 ne_fix: np.ndarray) -> np.ndarray:
    """For each fix taken while moving: its logged time minus the moment the true track came
    closest to its position (within 2 s before or after): SITL's GPS lag plus the dating."""
    out = []
    for tf, p in zip(t_fix, ne_fix, strict=True):
        near = np.abs(t - tf) <= 2.0
        if not near.any() or np.interp(tf, t, speed) < MOVING_M_S:
            continue
        k = np.argmin(np.linalg.norm(ne_true[near] - p, axis=1))
        out.append(tf - t[near][k])
    return np.asarray(out)


def score(fdir: Path) -> dict[str, Any]:
    """Ours and ArduPilot's against SIMSTATE (the whole flight once both have a solution, and
    its turns); velocity against ArduPilot's."""
    truth = read_log(fdir / "truth.bin").data(1)
    truth = truth[np.isfinite(truth["lat_deg"]) & (truth["lat_deg"] != 0)]
    ours = read_log(fdir / "estimator.bin").data(1)
    ours = ours[ours["aligned"] > 0]
    ap = read_log(fdir / "autopilot.bin").data(2)
    gps = read_log(fdir / "gps.bin").data(1)
    gps = gps[(gps["fix"] > 0) & np.isfinite(gps["lat_deg"])]
    frame = NedFrame(*SITL_HOME)

    t = truth["time_s"]
    q_true = quat_from_euler(truth["roll_rad"], truth["pitch_rad"], truth["yaw_rad"])
    ne_true = _ne(frame, truth["lat_deg"], truth["lon_deg"])
    j, w, ok_v = _interp_at(t, t - 1.0)  # true ground speed over the last second
    ne_back = (1 - w)[:, None] * ne_true[j - 1] + w[:, None] * ne_true[j]
    speed = np.where(ok_v, np.linalg.norm(ne_true - ne_back, axis=1), 0.0)

    ap_pos = np.isfinite(ap["lat_deg"]) & (ap["lat_deg"] != 0)
    start = max(float(ours["time_s"][0]), float(ap["time_s"][ap_pos][0]), float(t[0])) + WARMUP_S
    in_turn = np.abs(truth["roll_rad"]) > TURN_BANK_RAD

    q_ours, ok_o = interp_quat(ours["time_s"], quat_from_euler(
        ours["roll_rad"], ours["pitch_rad"], ours["yaw_rad"]), t)
    q_ap, ok_a = interp_quat(ap["time_s"], quat_from_euler(
        ap["roll_rad"], ap["pitch_rad"], ap["yaw_rad"]), t)
    ne_ours, ok_on = interp_cols(ours["time_s"], np.column_stack([ours["north_m"],
                                                                   ours["east_m"]]), t)
    # ArduPilot's position: the link logs the last GLOBAL_POSITION_INT with every ATTITUDE, so
    # only the rows where it changed are fresh (at most one ATTITUDE period, 40 ms, old)
    fresh = ap_pos & np.r_[True, (np.diff(ap["lat_deg"]) != 0) | (np.diff(ap["lon_deg"]) != 0)]
    apf = ap[fresh]
    ne_ap = _ne(frame, apf["lat_deg"], apf["lon_deg"])
    ne_true_at_ap, ok_ta = interp_cols(t, ne_true, apf["time_s"])
    turn_at_ap = np.abs(np.interp(apf["time_s"], t, truth["roll_rad"])) > TURN_BANK_RAD
    ne_gps = _ne(frame, gps["lat_deg"], gps["lon_deg"])
    ne_true_at_gps, ok_tg = interp_cols(t, ne_true, gps["time_s"])
    # velocity: ours at ArduPilot's fresh rows against ArduPilot's (no true velocity)
    v_ours, ok_ov = interp_cols(ours["time_s"], np.column_stack(
        [ours["vn_m_s"], ours["ve_m_s"], ours["vd_m_s"]]), apf["time_s"])
    v_ap = np.column_stack([apf["vn_m_s"], apf["ve_m_s"], apf["vd_m_s"]])
    v_gps, ok_gv = interp_cols(gps["time_s"], np.column_stack(
        [gps["vn_m_s"], gps["ve_m_s"]]), apf["time_s"])
    late = gps_dating_s(t, ne_true, speed, gps["time_s"], ne_gps)

    out: dict[str, Any] = {
        "window_start_s": round(start - float(t[0]), 1),
        "truth_start_from_home_m": float(np.linalg.norm(ne_true[0])),
        "gps_dating_s": {"n": int(len(late)), **({
            "median": float(np.median(late)), "p95": float(np.percentile(late, 95)),
            "max": float(late.max()), "over_0_3_s": int(np.sum(late > 0.3))} if len(late) else {})},
    }
    for name, m, m_ap in (("all", t >= start, apf["time_s"] >= start),
                          ("turns", (t >= start) & in_turn, (apf["time_s"] >= start) & turn_at_ap)):
        mo, ma = m & ok_o, m & ok_a
        mp, mv = m_ap & ok_ta, m_ap & ok_ov
        mg = (gps["time_s"] >= start) & ok_tg
        out[name] = {
            "scored_s": round(float(np.sum(m)) * float(np.median(np.diff(t))), 1),
            "ours": {
                "incl_deg": _stats(np.degrees(inclination_error_rad(q_ours[mo], q_true[mo]))),
                "heading_deg": _stats(np.degrees(heading_error_rad(q_ours[mo], q_true[mo]))),
                "hpos_m": _stats(np.linalg.norm(ne_ours[m & ok_on] - ne_true[m & ok_on],
                                                axis=1)),
                "vel_h_vs_ap_m_s": _stats(np.linalg.norm(v_ours[mv, :2] - v_ap[mv, :2],
                                                         axis=1)),
                "vel_d_vs_ap_m_s": _stats(v_ours[mv, 2] - v_ap[mv, 2]),
            },
            "ardupilot": {
                "incl_deg": _stats(np.degrees(inclination_error_rad(q_ap[ma], q_true[ma]))),
                "heading_deg": _stats(np.degrees(heading_error_rad(q_ap[ma], q_true[ma]))),
                "hpos_m": _stats(np.linalg.norm(ne_ap[mp] - ne_true_at_ap[mp], axis=1)),
            },
            "gps": {
                "hpos_m": _stats(np.linalg.norm(ne_gps[mg] - ne_true_at_gps[mg], axis=1)),
                "vel_h_vs_ap_m_s": _stats(np.linalg.norm(v_gps[mv & ok_gv] - v_ap[mv & ok_gv, :2],
                                                         axis=1)),
            },
        }
    return out


# ------------------------------------------------------------------------------ report


def _mean(flights: list[dict[str, Any]], *path: str) -> float:
    vals = []
    for f in flights:
        v: Any = f
        for p in path:
            v = v[p]
        vals.append(v)
    arr = np.asarray(vals, dtype=float)
    return float(np.nanmean(arr)) if np.isfinite(arr).any() else math.nan


def _f(v: float, digits: int = 2) -> str:
    return "–" if not math.isfinite(v) else f"{v:.{digits}f}"


def report(result: dict[str, Any]) -> str:
    lines: list[str] = []
    add = lines.append
    est = result["estimation"]
    add(f"## Beside ArduPlane's EKF3 (ArduPlane SITL, --speed {SPEED:g}, "
        f"{result['duration_s']:.0f} s flights in AUTO, {result['flights_per_setting']} per "
        "setting)\n")
    add("Against SIMSTATE (the SITL's own truth), mean over the flights of each flight's "
        f"figure. Scored from {WARMUP_S:g} s after both filters have a solution (ours aligns "
        "its heading once the take-off roll gives a GPS course) to the end; 'turns': the "
        f"samples of that window where the true bank exceeds {math.degrees(TURN_BANK_RAD):.0f} "
        "deg. ArduPilot's position only at the rows where GLOBAL_POSITION_INT was fresh.\n")
    add("| setting | window | filter | incl RMSE ° | incl p95 ° | incl max ° | heading RMSE ° "
        "| hpos RMSE m | hpos max m | incl RMSE ours / ArduPilot |")
    add("|---|---|---|---|---|---|---|---|---|---|")
    for setting in SETTINGS:
        fl = est[setting]
        for win in ("all", "turns"):
            inc_o = _mean(fl, "score", win, "ours", "incl_deg", "rmse")
            inc_a = _mean(fl, "score", win, "ardupilot", "incl_deg", "rmse")
            for who, label in (("ours", "ours"), ("ardupilot", "ArduPilot EKF3")):
                ratio = f"**{_f(inc_o / inc_a)}x**" if who == "ours" else ""
                add(f"| {setting} | {win} | {label} | "
                    f"{_f(_mean(fl, 'score', win, who, 'incl_deg', 'rmse'), 3)} | "
                    f"{_f(_mean(fl, 'score', win, who, 'incl_deg', 'p95'))} | "
                    f"{_f(_mean(fl, 'score', win, who, 'incl_deg', 'max'))} | "
                    f"{_f(_mean(fl, 'score', win, who, 'heading_deg', 'rmse'))} | "
                    f"{_f(_mean(fl, 'score', win, who, 'hpos_m', 'rmse'))} | "
                    f"{_f(_mean(fl, 'score', win, who, 'hpos_m', 'max'))} | {ratio} |")
        add(f"| {setting} | all | the GPS fix at its logged time (gps.bin) | – | – | – | – "
            "| "
            f"{_f(_mean(fl, 'score', 'all', 'gps', 'hpos_m', 'rmse'))} | "
            f"{_f(_mean(fl, 'score', 'all', 'gps', 'hpos_m', 'max'))} | |")
    add("\nHow each filter is told: ours, the autopilot's RAW_IMU (its first IMU, after "
        "ArduPilot's own low-pass, asked at 50 Hz, delivered at the rate in the per-flight table) "
        "and GPS_RAW_INT (5 Hz, dated by its own stamp through the link's clock map), with the "
        "estimator's default (thesis-tuned) parameters, no barometer, compass or airspeed; "
        "EKF3, its own two IMUs (SIM_IMU_COUNT 2, a lane each, EK3_IMU_MASK 3) sampled at 1 kHz "
        "and integrated over its 50 Hz main loop (SCHED_LOOP_RATE 50), GPS (5 Hz, 100 ms "
        "late: SIM_GPS1_LAG_MS), barometer, compass and airspeed.\n")
    add("GPS fix dating (moving fixes: the logged time minus the moment the true track "
        "passed the fix's position; SITL's fixes are the true position 100 ms late):\n")
    add("| setting | flight | fixes | median s | p95 s | max s | later than 0.3 s |")
    add("|---|---|---|---|---|---|---|")
    for setting in SETTINGS:
        for i, f in enumerate(est[setting]):
            g = f["score"]["gps_dating_s"]
            if g["n"]:
                add(f"| {setting} | {i + 1} | {g['n']} | {g['median']:.3f} | {g['p95']:.3f} | "
                    f"{g['max']:.3f} | {g['over_0_3_s']} |")
    add("\nVelocity: SIMSTATE has none, so ours is compared with ArduPilot's "
        "GLOBAL_POSITION_INT velocity (a reference, not the truth), at its fresh rows:\n")
    add("| setting | window | ours − ArduPilot, horizontal RMS m/s | vertical RMS m/s | "
        "the GPS fix − ArduPilot, horizontal RMS m/s |")
    add("|---|---|---|---|---|")
    for setting in SETTINGS:
        fl = est[setting]
        for win in ("all", "turns"):
            add(f"| {setting} | {win} | "
                f"{_f(_mean(fl, 'score', win, 'ours', 'vel_h_vs_ap_m_s', 'rmse'), 3)} | "
                f"{_f(_mean(fl, 'score', win, 'ours', 'vel_d_vs_ap_m_s', 'rmse'), 3)} | "
                f"{_f(_mean(fl, 'score', win, 'gps', 'vel_h_vs_ap_m_s', 'rmse'), 3)} |")
    add("\nPer flight (window 'all'):\n")
    add("| setting | flight | scored from s | scored s | autopilot speed-up | max alt m | "
        "IMU Hz | GPS fused / rejected | ours incl ° | EKF3 incl ° | ours heading ° | "
        "EKF3 heading ° | ours hpos m | EKF3 hpos m |")
    add("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for setting in SETTINGS:
        for i, f in enumerate(est[setting]):
            s = f["score"]["all"]
            c = f["estimator_counters"] or {}
            add(f"| {setting} | {i + 1} | {f['score']['window_start_s']} | {s['scored_s']} | "
                f"{f['autopilot_speed']} | {f['max_relative_alt_m']:.0f} | "
                f"{f['rates_hz'].get('estimator', 0):.1f} | "
                f"{c.get('gps_accepted', 0)} / {c.get('gps_rejected', 0)} | "
                f"{_f(s['ours']['incl_deg']['rmse'], 3)} | "
                f"{_f(s['ardupilot']['incl_deg']['rmse'], 3)} | "
                f"{_f(s['ours']['heading_deg']['rmse'])} | "
                f"{_f(s['ardupilot']['heading_deg']['rmse'])} | "
                f"{_f(s['ours']['hpos_m']['rmse'])} | {_f(s['ardupilot']['hpos_m']['rmse'])} |")
    every = [f for fl in est.values() for f in fl]
    add(f"\nArduPilot said 'AHRS: EKF3 active' in {sum(f['ekf3_active'] for f in every)} of "
        f"{len(every)} flights; thread restarts in all flights: "
        f"{sum(f['restarts'] for f in every)}.")
    add("\nThe consumer-MEMS setting (`SIM_*` after plane.parm): "
        + ", ".join(f"{k} {v:.4g}" for k, v in MEMS_OVERRIDES.items()) + ". Not raised: "
        + "; ".join(NOT_RAISED) + ".")

    cpu = result["cpu"]
    add(f"\n## Runtime CPU beside the autopilot ({cpu['pairs']} pairs, same run)\n")
    add("The `companion sim` process over each flight's steady part (a quarter in to the end), "
        "in ms of CPU per simulated second (and % of one core at the 5x speed-up); baseline: "
        "the same flight with the estimator and control law off.\n")
    add("| run | process: ms CPU per sim s | % of one core | runtime threads only: ms per sim s "
        "| ArduPlane SITL % of one core | IMU samples/sim s |")
    add("|---|---|---|---|---|---|")
    for key, label in (("full", "every thread (SITL defaults flights)"),
                       ("mems", "every thread (consumer-MEMS flights)"),
                       ("baseline", "baseline: estimator and control off")):
        fl = cpu[key]
        if not fl:
            continue
        add(f"| {label} | {_mean(fl, 'cpu', 'companion_ms_per_sim_s'):.1f} | "
            f"{_mean(fl, 'cpu', 'companion_pct_core'):.1f} | "
            f"{_mean(fl, 'cpu', 'runtime_ms_per_sim_s'):.1f} | "
            f"{_mean(fl, 'cpu', 'autopilot_pct_core'):.1f} | "
            f"{_mean(fl, 'imu_samples') / result['duration_s']:.1f} |")
    add(f"\nevery thread / baseline, whole process: **{cpu['ratio_full_over_baseline']:.2f}x**; "
        f"runtime threads only (the harness's unnamed threads left out): "
        f"**{cpu['runtime_ratio_full_over_baseline']:.2f}x**; the estimator and control law "
        f"cost {cpu['added_ms_per_sim_s']:.1f} ms of CPU per simulated second "
        f"({cpu['added_ms_per_sim_s'] / 10:.1f} % of one core in real time).\n")
    add("Per thread (ms of CPU per simulated second, mean over the flights):\n")
    add("| thread | every thread | baseline |")
    add("|---|---|---|")
    names = sorted({n for f in cpu["full"] + cpu["baseline"]
                    for n in f["cpu"]["threads_ms_per_sim_s"]},
                   key=lambda n: -np.mean([f["cpu"]["threads_ms_per_sim_s"].get(n, 0.0)
                                           for f in cpu["full"]]))
    for n in names:
        full = np.mean([f["cpu"]["threads_ms_per_sim_s"].get(n, 0.0) for f in cpu["full"]])
        base = np.mean([f["cpu"]["threads_ms_per_sim_s"].get(n, 0.0) for f in cpu["baseline"]])
        if max(full, base) >= 0.05:
            add(f"| {n} | {full:.2f} | {base:.2f} |")
    m = result["machine"]
    add(f"\n(load average {m['load_before']} before, {m['load_after']} after, on {m['nproc']} "
        f"CPUs; {result['wall_s']:.0f} s in all)")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one flight per setting")
    ap.add_argument("--flights", type=int, help="flights per setting (default 3; --quick 1)")
    ap.add_argument("--duration", type=float, default=DURATION_S, metavar="S",
                    help=f"simulated seconds a flight (default {DURATION_S:g})")
    ap.add_argument("--json", type=Path, metavar="PATH", help="write every figure here")
    ap.add_argument("--md", type=Path, metavar="PATH", help="write the tables here too")
    args = ap.parse_args()
    try:
        find_defaults(find_binary())
    except SitlNotFound as exc:
        print(f"autopilot_bench: {exc}", file=sys.stderr)
        return 2
    n = args.flights or (1 if args.quick else 3)
    res = Result("autopilot-estimation", ["companion", "gcs_bridge"], quick=args.quick)
    t0 = time.monotonic()
    flights: dict[str, list[dict[str, Any]]] = {s: [] for s in SETTINGS}
    baselines: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="autopilot-bench-") as tmp_name:
        tmp = Path(tmp_name)
        for i in range(n):
            # interleaved, so the CPU pair (defaults, baseline) flies under the same load
            for setting, baseline in (("defaults", False), ("defaults", True),
                                      ("consumer-mems", False)):
                label = f"{setting}-{i + 1}" + ("-baseline" if baseline else "")
                print(f"flight {label} ...", file=sys.stderr, flush=True)
                f = fly(tmp, label, setting, args.duration, baseline=baseline)
                if baseline:
                    baselines.append(f)
                    continue
                f["score"] = score(Path(f["flight_dir"]))
                flights[setting].append(f)
    wall_s = time.monotonic() - t0
    full_ms = _mean(flights["defaults"], "cpu", "companion_ms_per_sim_s")
    base_ms = _mean(baselines, "cpu", "companion_ms_per_sim_s")
    result: dict[str, Any] = {
        "command": "python bench/autopilot_bench.py" + (" --quick" if args.quick else "")
                   + (f" --flights {args.flights}" if args.flights else "")
                   + (f" --duration {args.duration:g}" if args.duration != DURATION_S else ""),
        "commit": res.commit,
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": {"nproc": len(os.sched_getaffinity(0)), "cpu_count": os.cpu_count(),
                    "python": platform.python_version(), "platform": platform.platform(),
                    "load_before": res.load_before,
                    "load_after": [round(v, 2) for v in os.getloadavg()]},
        "wall_s": wall_s,
        "speed": SPEED, "duration_s": args.duration, "flights_per_setting": n,
        "sitl_home": SITL_HOME,
        "estimator_params": {f"{ESTIMATOR_PARAM_PREFIX}_{k}": v for k, v in
                             estimator_param_defaults(ESTIMATOR_PARAM_PREFIX).items()},
        "mems_overrides": MEMS_OVERRIDES, "not_raised": NOT_RAISED,
        "estimation": flights,
        "cpu": {"pairs": len(baselines), "full": flights["defaults"],
                "mems": flights["consumer-mems"], "baseline": baselines,
                "full_ms_per_sim_s": full_ms, "baseline_ms_per_sim_s": base_ms,
                "ratio_full_over_baseline": full_ms / base_ms,
                "runtime_ratio_full_over_baseline":
                    _mean(flights["defaults"], "cpu", "runtime_ms_per_sim_s")
                    / _mean(baselines, "cpu", "runtime_ms_per_sim_s"),
                "added_ms_per_sim_s": full_ms - base_ms},
    }
    with res.capture():
        text = report(result)
        print(text)
    if args.md is not None:
        header = (f"<!-- ARDUPILOT_SITL=<arduplane> {result['command']} (commit "
                  f"{result['commit'][:7]}; {result['machine']['nproc']}-core machine shared "
                  "with other work) -->\n\n")
        args.md.write_text(header + text + "\n", encoding="utf-8")
    # the CPU part names its flights (they are in "estimation" already)
    saved = {**result, "cpu": {**result["cpu"], **{
        k: [f["label"] for f in result["cpu"][k]] for k in ("full", "mems")}}}
    # a flight's directory was a temporary one: its name only, no machine's path
    text_json = json.dumps(saved, indent=1, default=float)
    text_json = re.sub(r'"flight_dir": "[^"]*/([^"/]+)"', r'"flight_dir": "\1"', text_json)
    if args.json is not None:
        args.json.write_text(text_json + "\n", encoding="utf-8")
    res.data = {k: v for k, v in json.loads(text_json).items()
                if k not in ("command", "commit", "date")}
    res.write()
    return 0


if __name__ == "__main__":
    sys.exit(main())
