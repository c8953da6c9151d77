"""JSBSim flight model: the adapter between JSBSim and the ground truth of a simulated flight.

It hides JSBSim's imperial units and property names behind the one SI dataclass everything else
in SITL is judged against (`companion.sim.truth.TruthState`, the project's frames: NED, body
axes x forward, y right, z down), and flies the aircraft of `companion.sim.aircraft`; both live
apart so that what reads the truth or the catalogue needs no JSBSim.

The model runs at a fixed rate that is a whole multiple of 100 Hz, so the 100 Hz IMU frames of
the device contract fall exactly on model steps (JSBSim's customary 120 Hz would not).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import jsbsim

from companion.core.geo import NedFrame
from companion.core.mathutil import clamp
from companion.sim.aircraft import DEFAULT_AIRCRAFT, AircraftSpec, resolve_aircraft
from companion.sim.truth import TruthState

log = logging.getLogger(__name__)

FT_M = 0.3048
"""Metres per foot."""
KT_M_S = 1852.0 / 3600.0
"""Metres per second per knot."""

GROUND_CONTACT_M = 1.0
"""Height above the terrain (sea level here) below which the flight counts as crashed: no
scenario lands, so touching the ground is always the end of the flight."""

TRIM_METHODS = ("full", "settle")
"""Trim strategies tried in order by default; see :class:`FlightModel`."""


class FlightModelError(RuntimeError):
    """JSBSim could not load, start or continue the simulation."""


@dataclass(frozen=True, slots=True)
class Controls:
    """Normalised control commands in JSBSim's sign convention.

    aileron +1 rolls right, elevator +1 pitches nose down (stick forward), rudder +1 yaws nose
    left (JSBSim's convention, opposite to the right pedal), throttle 0 idle .. 1 full.
    """

    aileron: float
    elevator: float
    rudder: float
    throttle: float


# JSBSim properties read for the truth, in the order _read_truth unpacks them.
_TRUTH_PROPS = (
    "simulation/sim-time-sec",
    "position/lat-geod-deg",
    "position/long-gc-deg",
    "position/h-sl-meters",
    "velocities/v-north-fps",
    "velocities/v-east-fps",
    "velocities/v-down-fps",
    "attitude/phi-rad",
    "attitude/theta-rad",
    "attitude/psi-rad",
    "velocities/pi-rad_sec",
    "velocities/qi-rad_sec",
    "velocities/ri-rad_sec",
    "forces/fbx-total-lbs",
    "forces/fby-total-lbs",
    "forces/fbz-total-lbs",
    "inertia/mass-slugs",
    "velocities/vtrue-fps",
    "aero/alpha-rad",
    "aero/beta-rad",
)


def _finite(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"FlightModel: {name} must be finite, got {value!r}")
    return value


def jsbsim_root_dir() -> str:
    """The directory of the aircraft and engine definitions that the jsbsim package ships.

    They sit beside the imported module (``jsbsim/aircraft``, ``jsbsim/engine``).
    ``jsbsim.get_default_root_dir()`` looks only in the interpreter's site-packages
    directories (``site.getsitepackages()``, the user site), so it fails when jsbsim is
    imported from anywhere else: ``pip install --target``, PYTHONPATH, a ``.pth`` path line.
    """
    here = os.path.dirname(os.path.abspath(jsbsim.__file__ or ""))
    if os.path.isdir(os.path.join(here, "aircraft")):
        return here
    return str(jsbsim.get_default_root_dir())


class FlightModel:
    """A JSBSim aircraft started airborne and trimmed, stepped at a fixed rate.

    Trim: ``trim_methods`` are tried in order until one succeeds. ``"full"`` is JSBSim's own
    six-axis trim. ``"settle"`` is the fallback for when it fails: the aircraft is flown by a
    simple integrating stabiliser until steady, the settled angle of attack and controls are
    recorded, and the flight restarts from the requested point with them, after one more
    JSBSim trim from that close guess. (JSBSim's longitudinal-only trim is no fallback: the
    untrimmed propeller torque rolls a hands-off Cessna into a spiral dive within 30 s.) The
    method used is in :attr:`trim_method`: ``"full"``, ``"settle+full"`` or ``"settle"``.
    After trim, the aileron, rudder and elevator offsets are moved into JSBSim's trim-tab
    properties so that centred controls hold the trimmed state, as a pilot trims a real
    aircraft: :attr:`trim_controls` is then (0, 0, 0, throttle).

    Wind: ``wind_ned_m_s`` is the velocity of the air mass (towards north, east, down). The
    aircraft starts with the requested airspeed and heading through the air; the horizontal
    wind is part of the trim, a vertical component starts acting just after it. Turbulence
    (JSBSim's MIL-F-8785C model) is off unless ``turbulence_severity`` (1..7) is given, seeded
    from ``seed``. Fuel is frozen by default so that long flights keep one mass.
    """

    def __init__(
        self,
        aircraft: str | AircraftSpec = DEFAULT_AIRCRAFT,
        *,
        lat_deg: float = 43.68,
        lon_deg: float = 10.39,
        alt_m: float = 300.0,
        airspeed_m_s: float | None = None,
        heading_deg: float = 0.0,
        wind_ned_m_s: Sequence[float] = (0.0, 0.0, 0.0),
        turbulence_severity: int = 0,
        seed: int = 0,
        rate_hz: int = 100,
        trim_methods: Sequence[str] = TRIM_METHODS,
        freeze_fuel: bool = True,
        root_dir: str | None = None,
    ) -> None:
        self.spec = resolve_aircraft(aircraft)
        self._lat0_deg = _finite("lat_deg", lat_deg)
        self._lon0_deg = _finite("lon_deg", lon_deg)
        self._alt0_m = _finite("alt_m", alt_m)
        if not -90.0 <= self._lat0_deg <= 90.0:
            raise ValueError(f"FlightModel: lat_deg must be within -90..90, got {lat_deg!r}")
        if not -180.0 <= self._lon0_deg <= 360.0:
            raise ValueError(f"FlightModel: lon_deg must be within -180..360, got {lon_deg!r}")
        if not 30.0 <= self._alt0_m <= 10000.0:
            raise ValueError(
                f"FlightModel: alt_m must be within 30..10000 m (start airborne), got {alt_m!r}"
            )
        speed = self.spec.cruise_airspeed_m_s if airspeed_m_s is None else airspeed_m_s
        self._airspeed0_m_s = _finite("airspeed_m_s", speed)
        if not self.spec.stall_airspeed_m_s < self._airspeed0_m_s < self.spec.never_exceed_m_s:
            raise ValueError(
                f"FlightModel: airspeed_m_s for {self.spec.name} must be within "
                f"{self.spec.stall_airspeed_m_s}..{self.spec.never_exceed_m_s} m/s, got {speed!r}"
            )
        self._heading0_deg = _finite("heading_deg", heading_deg) % 360.0
        wind = tuple(wind_ned_m_s)
        if len(wind) != 3:
            raise ValueError(f"FlightModel: wind_ned_m_s needs 3 components, got {len(wind)}")
        self._wind_ned_m_s = tuple(_finite(f"wind_ned_m_s[{i}]", w) for i, w in enumerate(wind))
        if math.hypot(*self._wind_ned_m_s) >= 0.8 * self._airspeed0_m_s:
            raise ValueError(
                f"FlightModel: wind {math.hypot(*self._wind_ned_m_s):.1f} m/s is too strong for "
                f"an airspeed of {self._airspeed0_m_s:.1f} m/s"
            )
        if not (isinstance(turbulence_severity, int) and 0 <= turbulence_severity <= 7):
            raise ValueError(
                f"FlightModel: turbulence_severity must be an int 0..7, got {turbulence_severity!r}"
            )
        if not (isinstance(rate_hz, int) and rate_hz >= 100 and rate_hz % 100 == 0):
            raise ValueError(
                f"FlightModel: rate_hz must be a whole multiple of 100 (IMU at 100 Hz), got "
                f"{rate_hz!r}"
            )
        methods = tuple(trim_methods)
        bad = [m for m in methods if m not in TRIM_METHODS]
        if not methods or bad:
            raise ValueError(
                f"FlightModel: trim_methods must be taken from {TRIM_METHODS}, got {methods!r}"
            )
        self.rate_hz = rate_hz
        self.dt_s = 1.0 / rate_hz
        self._turbulence_severity = turbulence_severity
        self._seed = int(seed)
        self._freeze_fuel = freeze_fuel
        self.frame = NedFrame(self._lat0_deg, self._lon0_deg, self._alt0_m)
        self._fdm = self._load(root_dir)
        self._bind_nodes()
        self._steps = 0
        self._target_steps = 0.0
        self.trim_method = self._trim(methods)
        self.trim_controls = self._centre_trim()
        log.info(
            "flight model %s trimmed by %s at %.0f m, %.1f m/s: throttle %.2f",
            self.spec.name,
            self.trim_method,
            self._alt0_m,
            self._airspeed0_m_s,
            self.trim_controls.throttle,
        )

    # ----------------------------------------------------------------------------------------
    # set-up

    def _load(self, root_dir: str | None) -> jsbsim.FGFDMExec:
        # JSBSim's banner and per-step chatter go to the C++ stdout; the level is process-wide.
        jsbsim.FGJSBBase().debug_lvl = 0
        root = root_dir if root_dir is not None else jsbsim_root_dir()
        model_dir = os.path.join(root, "aircraft", self.spec.jsbsim_model)
        if not os.path.isdir(model_dir):
            raise FlightModelError(
                f"JSBSim aircraft {self.spec.jsbsim_model!r} not found: no directory {model_dir}"
            )
        fdm = jsbsim.FGFDMExec(root)
        fdm.set_debug_level(0)
        try:
            loaded = fdm.load_model(self.spec.jsbsim_model)
        except Exception as exc:  # JSBSim raises its own exception types from C++
            raise FlightModelError(
                f"JSBSim failed to load aircraft {self.spec.jsbsim_model!r} from {root}: {exc}"
            ) from exc
        if not loaded:
            raise FlightModelError(
                f"JSBSim failed to load aircraft {self.spec.jsbsim_model!r} from {root}"
            )
        fdm.set_dt(self.dt_s)
        # Some models declare file outputs (c172x writes JSBout172B.csv): never write files.
        fdm.disable_output()
        return fdm

    def _bind_nodes(self) -> None:
        # Property nodes skip the name lookup of fdm[...] on every step.
        pm = self._fdm.get_property_manager()
        self._n_engines = int(self._fdm.get_propulsion().get_num_engines())
        names = list(_TRUTH_PROPS) + [
            "position/h-agl-ft",
            "fcs/aileron-cmd-norm",
            "fcs/elevator-cmd-norm",
            "fcs/rudder-cmd-norm",
        ]
        names += [f"fcs/throttle-cmd-norm[{i}]" for i in range(self._n_engines)]
        nodes: dict[str, jsbsim.FGPropertyNode] = {}
        for name in names:
            node = pm.get_node(name, False)
            if node is None:
                raise FlightModelError(
                    f"JSBSim aircraft {self.spec.jsbsim_model!r} has no property {name!r}"
                )
            nodes[name] = node
        self._truth_nodes = [nodes[n] for n in _TRUTH_PROPS]
        self._agl_node = nodes["position/h-agl-ft"]
        self._ail_node = nodes["fcs/aileron-cmd-norm"]
        self._elev_node = nodes["fcs/elevator-cmd-norm"]
        self._rud_node = nodes["fcs/rudder-cmd-norm"]
        self._thr_nodes = [nodes[f"fcs/throttle-cmd-norm[{i}]"] for i in range(self._n_engines)]
        rpm = pm.get_node("propulsion/engine[0]/propeller-rpm", False) if self._n_engines else None
        self._rpm_node = rpm

    def _apply_ic(self, theta_deg: float, throttle: float) -> None:
        """Load the requested start point into JSBSim and initialise the state from it."""
        f = self._fdm
        f["ic/lat-geod-deg"] = self._lat0_deg
        f["ic/long-gc-deg"] = self._lon0_deg
        f["ic/h-sl-ft"] = self._alt0_m / FT_M
        f["ic/terrain-elevation-ft"] = 0.0
        f["ic/psi-true-deg"] = self._heading0_deg
        f["ic/theta-deg"] = theta_deg
        f["ic/phi-deg"] = 0.0
        f["ic/p-rad_sec"] = 0.0
        f["ic/q-rad_sec"] = 0.0
        f["ic/r-rad_sec"] = 0.0
        # Ground velocity = air velocity along the heading + wind. The IC wind must be set after
        # the ground velocity, magnitude before direction: JSBSim keeps the ground velocity and
        # rotates an existing wind vector, so a zero wind has no direction to set.
        hdg = math.radians(self._heading0_deg)
        wn, we, _ = self._wind_ned_m_s
        f["ic/vn-fps"] = (self._airspeed0_m_s * math.cos(hdg) + wn) / FT_M
        f["ic/ve-fps"] = (self._airspeed0_m_s * math.sin(hdg) + we) / FT_M
        f["ic/vd-fps"] = 0.0
        horizontal = math.hypot(wn, we)
        if horizontal > 0.0:
            f["ic/vw-mag-fps"] = horizontal / FT_M
            f["ic/vw-dir-deg"] = math.degrees(math.atan2(we, wn))
        if self._turbulence_severity:
            f["atmosphere/turb-type"] = 3  # MIL-F-8785C / MIL-HDBK-1797 (Tustin)
            # Low-altitude intensity follows the wind at 20 ft: MIL-F-8785C pairs light,
            # moderate and severe turbulence with 15, 30 and 45 kt, and JSBSim's severity
            # index (its probability-of-exceedance curve) names 3 light, 4 moderate, 6 severe.
            w20_kt = (15.0, 15.0, 15.0, 30.0, 30.0, 45.0, 45.0)[self._turbulence_severity - 1]
            f["atmosphere/turbulence/milspec/windspeed_at_20ft_AGL-fps"] = w20_kt * KT_M_S / FT_M
            f["atmosphere/turbulence/milspec/severity"] = self._turbulence_severity
        else:
            f["atmosphere/turbulence/milspec/severity"] = 0
        for prop in ("simulation/randomseed", "atmosphere/randomseed"):
            if self._has(prop):
                f[prop] = self._seed
        for name in ("fcs/aileron-cmd-norm", "fcs/elevator-cmd-norm", "fcs/rudder-cmd-norm"):
            f[name] = 0.0
        for prop in ("fcs/pitch-trim-cmd-norm", "fcs/roll-trim-cmd-norm", "fcs/yaw-trim-cmd-norm"):
            if self._has(prop):
                f[prop] = 0.0
        for i in range(self._n_engines):
            f[f"fcs/throttle-cmd-norm[{i}]"] = throttle
            if self._has(f"fcs/mixture-cmd-norm[{i}]"):
                f[f"fcs/mixture-cmd-norm[{i}]"] = 1.0
        if not f.run_ic():
            raise FlightModelError(f"JSBSim refused the initial conditions of {self.spec.name}")
        f["propulsion/set-running"] = -1
        if self._freeze_fuel:
            f["propulsion/fuel_freeze"] = 1

    def _has(self, prop: str) -> bool:
        return self._fdm.get_property_manager().hasNode(prop)

    def _trim(self, methods: Sequence[str]) -> str:
        failures = []
        for method in methods:
            self._apply_ic(theta_deg=0.0, throttle=0.6)
            try:
                if method == "settle":
                    used = self._settle()
                else:
                    self._fdm.do_trim(1)  # JSBSim's full trim (all six axes)
                    used = method
            except Exception as exc:  # JSBSim's TrimFailureError derives from its own base
                failures.append(f"{method}: {exc}")
                log.warning("trim %s of %s failed: %s", method, self.spec.name, exc)
                continue
            if self._state_is_sane():
                self._reset_clock()
                return used
            failures.append(f"{method}: non-finite or implausible state after trim")
        raise FlightModelError(
            f"could not trim {self.spec.name} at {self._alt0_m} m, {self._airspeed0_m_s} m/s: "
            + "; ".join(failures)
        )

    def _reset_clock(self) -> None:
        self._t0_s = float(self._fdm["simulation/sim-time-sec"])
        self._steps = 0
        self._target_steps = 0.0

    def _state_is_sane(self) -> bool:
        values = [node.get_double_value() for node in self._truth_nodes]
        if not all(math.isfinite(v) for v in values):
            return False
        airspeed = self._fdm["velocities/vtrue-fps"] * FT_M
        return abs(airspeed - self._airspeed0_m_s) < 0.2 * self._airspeed0_m_s

    def _settle(self, max_s: float = 120.0, window_s: float = 5.0, retrim: bool = True) -> str:
        """Fallback trim: fly wings-level at the start altitude and speed, then restart there.

        A deliberately plain stabiliser with an integrator on every axis, so that once it is
        steady its control positions are the trim ones, whatever the aircraft. It only has to
        find the steady state, not fly well. The settled state then seeds one more attempt at
        JSBSim's trim (which often succeeds from a close guess); if that fails too, the settled
        controls are used as they are.
        """
        f = self._fdm
        dt = self.dt_s
        window = int(window_s * self.rate_hz)
        i_pitch = i_elev = i_ail = i_rud = 0.0
        i_thr = 0.6
        sums = [0.0] * 5
        count = 0
        for _ in range(int(max_s * self.rate_hz)):
            phi = f["attitude/phi-rad"]
            theta = f["attitude/theta-rad"]
            p = f["velocities/p-rad_sec"]
            q = f["velocities/q-rad_sec"]
            alt_err = self._alt0_m - f["position/h-sl-meters"]
            speed_err = self._airspeed0_m_s - f["velocities/vtrue-fps"] * FT_M
            climb = -f["velocities/v-down-fps"] * FT_M
            ay = f["forces/fby-total-lbs"] / f["inertia/mass-slugs"] * FT_M
            climb_err = min(max(0.2 * alt_err, -2.0), 2.0) - climb
            i_pitch = min(max(i_pitch + 0.02 * climb_err * dt, -0.3), 0.3)
            theta_err = min(max(i_pitch + 0.02 * climb_err, -0.3), 0.3) - theta
            i_elev = min(max(i_elev + 0.5 * theta_err * dt, -1.0), 1.0)
            i_ail = min(max(i_ail - 0.5 * phi * dt, -1.0), 1.0)
            # JSBSim rudder +1 yaws the nose left, which pushes the side force to the left.
            i_rud = min(max(i_rud + 0.05 * ay * dt, -1.0), 1.0)
            i_thr = min(max(i_thr + 0.02 * speed_err * dt, 0.0), 1.0)
            aileron = min(max(-1.5 * phi - 0.3 * p + i_ail, -1.0), 1.0)
            elevator = min(max(-(2.0 * theta_err - 0.5 * q + i_elev), -1.0), 1.0)
            rudder = min(max(0.1 * ay + i_rud, -1.0), 1.0)
            throttle = min(max(i_thr + 0.05 * speed_err, 0.0), 1.0)
            self._write_controls(aileron, elevator, rudder, throttle)
            if not f.run():
                raise FlightModelError("JSBSim stopped while settling")
            steady = (
                abs(alt_err) < 3.0
                and abs(speed_err) < 0.2
                and abs(climb) < 0.1
                and abs(phi) < 0.01
                and abs(p) + abs(q) + abs(f["velocities/r-rad_sec"]) < 0.01
            )
            if not steady:
                sums = [0.0] * 5
                count = 0
                continue
            for i, v in enumerate((f["aero/alpha-deg"], aileron, elevator, rudder, throttle)):
                sums[i] += v
            count += 1
            if count >= window:
                break
        else:
            raise FlightModelError(f"no steady flight found within {max_s:.0f} s of settling")
        alpha_deg, aileron, elevator, rudder, throttle = (s / count for s in sums)
        settled = (aileron, elevator, rudder)

        def restart() -> None:
            self._apply_ic(theta_deg=alpha_deg, throttle=throttle)
            self._write_controls(*settled, throttle)
            # Spin the engines up to the settled throttle, or the restart would begin with a
            # thrust transient that excites the phugoid.
            self._fdm.get_propulsion().get_steady_state()

        restart()
        if not retrim:
            return "settle"
        try:
            f.do_trim(1)
        except Exception as exc:
            log.info(
                "JSBSim trim from the settled state failed too (%s): using the settled one", exc
            )
            restart()
            return "settle"
        return "settle+full"

    def _centre_trim(self) -> Controls:
        """Move aileron/rudder trim into the trim tabs so centred controls stay trimmed."""
        f = self._fdm
        for cmd, tab in (
            ("fcs/aileron-cmd-norm", "fcs/roll-trim-cmd-norm"),
            ("fcs/rudder-cmd-norm", "fcs/yaw-trim-cmd-norm"),
            ("fcs/elevator-cmd-norm", "fcs/pitch-trim-cmd-norm"),
        ):
            if self._has(tab):
                f[tab] = f[tab] + f[cmd]
                f[cmd] = 0.0
        return Controls(
            aileron=float(f["fcs/aileron-cmd-norm"]),
            elevator=float(f["fcs/elevator-cmd-norm"]),
            rudder=float(f["fcs/rudder-cmd-norm"]),
            throttle=float(f["fcs/throttle-cmd-norm[0]"]),
        )

    # ----------------------------------------------------------------------------------------
    # public API

    @property
    def time_s(self) -> float:
        """Simulated time since the trimmed start."""
        return self._steps * self.dt_s

    @property
    def wind_ned_m_s(self) -> tuple[float, float, float]:
        """The steady wind the model was started with (air-mass velocity, NED)."""
        wn, we, wd = self._wind_ned_m_s
        return (wn, we, wd)

    def set_controls(self, aileron: float, elevator: float, rudder: float, throttle: float) -> None:
        """Command the surfaces and throttle (JSBSim convention, see :class:`Controls`).

        Values are clipped to -1..1 (throttle 0..1), as a servo's travel would clip them.
        """
        a = clamp(_finite("aileron", aileron), -1.0, 1.0)
        e = clamp(_finite("elevator", elevator), -1.0, 1.0)
        r = clamp(_finite("rudder", rudder), -1.0, 1.0)
        t = clamp(_finite("throttle", throttle), 0.0, 1.0)
        self._write_controls(a, e, r, t)

    def _write_controls(self, a: float, e: float, r: float, t: float) -> None:
        self._ail_node.set_double_value(a)
        self._elev_node.set_double_value(e)
        self._rud_node.set_double_value(r)
        for node in self._thr_nodes:
            node.set_double_value(t)

    def controls(self) -> Controls:
        """The commands currently applied."""
        return Controls(
            aileron=self._ail_node.get_double_value(),
            elevator=self._elev_node.get_double_value(),
            rudder=self._rud_node.get_double_value(),
            throttle=self._thr_nodes[0].get_double_value(),
        )

    def step(self, dt_s: float) -> int:
        """Advance the simulation by ``dt_s`` seconds; return the number of model steps run.

        Time is kept as a running target so that steps that are not a multiple of the model
        period (say 1/30 s frames) neither drift nor round away: over many calls the model
        advances exactly by the sum of ``dt_s``. Raises :class:`FlightModelError` if the state
        turns non-finite or the aircraft hits the ground.
        """
        dt_s = _finite("dt_s", dt_s)
        if not 0.0 <= dt_s <= 3600.0:
            raise ValueError(f"FlightModel.step: dt_s must be within 0..3600 s, got {dt_s!r}")
        self._target_steps += dt_s * self.rate_hz
        n = int(math.floor(self._target_steps - self._steps + 1e-6))
        run = self._fdm.run
        agl = self._agl_node.get_double_value
        floor_ft = GROUND_CONTACT_M / FT_M
        for _ in range(n):
            if not run():
                raise FlightModelError(f"JSBSim stopped at t={self.time_s:.2f} s")
            self._steps += 1
            if not agl() >= floor_ft:  # also catches a state gone NaN
                self._raise_lost()
        return n

    def _raise_lost(self) -> None:
        if not math.isfinite(self._agl_node.get_double_value()):
            raise FlightModelError(f"JSBSim state became non-finite at t={self.time_s:.2f} s")
        s = self.truth()
        raise FlightModelError(
            f"{self.spec.name} hit the ground at t={self.time_s:.2f} s, {s.airspeed_m_s:.1f} m/s, "
            f"{s.north_m:.0f} m north and {s.east_m:.0f} m east of the start"
        )

    def truth(self) -> TruthState:
        """The true state now, in SI units and the project's frames."""
        (
            _t,
            lat,
            lon,
            alt,
            vn,
            ve,
            vd,
            phi,
            theta,
            psi,
            p,
            q,
            r,
            fx,
            fy,
            fz,
            mass,
            vt,
            alpha,
            beta,
        ) = [node.get_double_value() for node in self._truth_nodes]
        north, east, down = self.frame.to_ned(lat, lon, alt)
        # Total non-gravitational force over mass: lbf/slug is ft/s^2.
        k = FT_M / mass
        if psi > math.pi:
            psi -= 2.0 * math.pi
        return TruthState(
            time_s=self._steps * self.dt_s,
            lat_deg=lat,
            lon_deg=lon,
            alt_m=alt,
            north_m=north,
            east_m=east,
            down_m=down,
            vn_m_s=vn * FT_M,
            ve_m_s=ve * FT_M,
            vd_m_s=vd * FT_M,
            roll_rad=phi,
            pitch_rad=theta,
            yaw_rad=psi,
            p_rad_s=p,
            q_rad_s=q,
            r_rad_s=r,
            ax_m_s2=fx * k,
            ay_m_s2=fy * k,
            az_m_s2=fz * k,
            airspeed_m_s=vt * FT_M,
            alpha_rad=alpha,
            beta_rad=beta,
        )

    def propeller_rpm(self) -> float:
        """The first engine's propeller speed (rev/min), which drives the IMU's vibration;
        0 for a model without one."""
        node = self._rpm_node
        return node.get_double_value() if node is not None else 0.0

    def property(self, name: str) -> float:
        """Read any JSBSim property (diagnostics and tests; not part of the truth contract)."""
        try:
            return float(self._fdm[name])
        except Exception as exc:
            raise KeyError(f"JSBSim has no property {name!r}") from exc
