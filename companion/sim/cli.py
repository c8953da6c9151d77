"""`companion sim`: a simulated flight with every part of the runtime running."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from companion.sim.runner import SimOptions

log = logging.getLogger(__name__)


def cmd_sim(args: argparse.Namespace) -> int:
    from companion.cli_common import config_from_args, print_summary
    from companion.core.clock import every
    from companion.runtime import status_line

    try:
        import jsbsim  # noqa: F401
    except ImportError:
        # on an aircraft's computer JSBSim is not needed (and has no aarch64 wheel)
        print("companion sim: the flight model needs JSBSim, which is not installed: "
              "pip install 'uav-companion[sim]' (docs/deploy.md)", file=sys.stderr)
        return 2
    from companion.sim.runner import (
        CAMERA_NEEDS_LEGACY,
        FAST_SCALE,
        SimError,
        run_fleet,
        run_sim,
    )
    from companion.sim.scenarios import SCENARIOS

    if args.scenario not in SCENARIOS:
        print(f"companion sim: unknown scenario {args.scenario!r} ({', '.join(SCENARIOS)})",
              file=sys.stderr)
        return 2
    from companion.sim.profiles import resolve_sensors

    try:
        resolve_sensors(args.imu_profile, args.gps_profile, args.turbulence,
                        no_noise=args.no_noise, gps_latency_s=args.gps_latency)
    except ValueError as exc:
        print(f"companion sim: {exc}", file=sys.stderr)
        return 2
    from companion.sim.faults import FAULT_KINDS

    for kind in FAULT_KINDS:
        for text in getattr(args, kind.dest):
            try:
                kind.parse(text)
            except ValueError as exc:
                print(f"companion sim: {exc}", file=sys.stderr)
                return 2
    if args.campaign is not None and not args.autopilot:
        return _campaign(args)
    if args.vehicles > 1:
        argv = [a for a in sys.argv[1:]]
        base = _strip(argv, ("--vehicles", "--mavlink-port-step"), takes_value=True)
        return run_fleet(base, args.vehicles, args.legacy_listen or 5500,
                         mavlink_port_step=args.mavlink_port_step)
    if args.autopilot:
        return _with_autopilot(args)
    cfg = config_from_args(args)
    if args.horizon_camera != "off" and not args.lockstep and not cfg.legacy.enabled:
        print(f"companion sim: {CAMERA_NEEDS_LEGACY}", file=sys.stderr)
        return 2
    if not args.legacy_dest and not _configured(args, "legacy.dest"):
        # a simulation stays on this machine: no broadcast onto the network
        cfg.legacy.dest = "127.0.0.1:5501"
    if not _configured(args, "legacy.bind"):
        cfg.legacy.bind = "127.0.0.1"
    scale = args.speed if args.speed else (FAST_SCALE if args.fast else 1.0)
    sim = sim_options(args, scale)

    def live(rt: object) -> None:
        if sys.stderr.isatty() and args.verbose == 0:
            mgr = rt.manager  # type: ignore[attr-defined]
            mgr.on_tick.append(every(1.0, lambda: print(
                "\r" + status_line(mgr)[:160], end="", file=sys.stderr, flush=True)))

    try:
        if args.lockstep:
            from companion.core.lockstep import LockstepError
            from companion.sim.lockstep import lockstep_problems, run_lockstep

            problems = lockstep_problems(args.thread_fault, args.clock_step)
            if problems:
                print(f"companion sim: --lockstep: {problems[0]}", file=sys.stderr)
                return 2
            try:
                summary = run_lockstep(cfg, sim, args.duration, on_runtime=live)
            except LockstepError as exc:
                print(f"companion sim: --lockstep: {exc}", file=sys.stderr)
                return 1
        else:
            summary = run_sim(cfg, sim, args.duration, on_runtime=live)
    except SimError as exc:
        print(f"companion sim: {exc}", file=sys.stderr)
        return 1
    if sys.stderr.isatty():
        print(file=sys.stderr)
    print_summary(summary, args.json)
    if summary.get("escalated"):
        from companion.watchdog.manager import EXIT_ESCALATED

        print(f"companion sim: thread {summary['escalated']} failed and escalated "
              f"(exit {EXIT_ESCALATED})", file=sys.stderr)
        return EXIT_ESCALATED
    return 0


def _with_autopilot(args: argparse.Namespace) -> int:
    """``companion sim --autopilot arduplane``: the real autopilot flies, the companion beside
    it (companion.sim.autopilot_flight); the JSBSim world and its options are not used."""
    from companion.cli_common import config_from_args, print_summary
    from companion.sim.ardupilot import SitlError
    from companion.sim.autopilot_flight import AutopilotSimOptions, run_with_arduplane

    if args.lockstep or args.campaign is not None:
        print("companion sim: --autopilot flies on the autopilot's own clock: it takes neither "
              "--lockstep nor --campaign", file=sys.stderr)
        return 2
    cfg = config_from_args(args)
    if not args.legacy_dest and not _configured(args, "legacy.dest"):
        cfg.legacy.dest = "127.0.0.1:5501"
    if not _configured(args, "legacy.bind"):
        cfg.legacy.bind = "127.0.0.1"
    speed = args.speed if args.speed else 1.0
    try:
        # in a fleet (--vehicles K) aircraft i is its own SITL instance (-I i-1, its own ports)
        # with the system id of its vehicle id
        options = AutopilotSimOptions(binary=args.autopilot_binary,
                                      defaults=args.autopilot_defaults, speedup=speed,
                                      mode=args.autopilot_mode, instance=args.seed_offset,
                                      sysid=cfg.vehicle.id)
        summary = run_with_arduplane(cfg, options, args.duration)
    except (SitlError, ValueError) as exc:
        print(f"companion sim: {exc}", file=sys.stderr)
        return 2
    print_summary(summary, args.json)
    return 0


def sim_options(args: argparse.Namespace, scale: float) -> SimOptions:
    """The simulated world of one aircraft from its command line. In a fleet, aircraft i is
    started with ``--seed-offset i-1``: its own pilot jitter, air and sensor noise, and with
    ``--imu-seed N`` its own part too (N + i - 1), as K aircraft carry K IMUs."""
    # imported here, as in cmd_sim: the runner is loaded only once JSBSim is known to be there
    from companion.sim.runner import SimOptions  # noqa: F811

    imu_seed = None if args.imu_seed is None else args.imu_seed + args.seed_offset
    return SimOptions(scenario=args.scenario, seed=args.seed + args.seed_offset,
                      aircraft=args.aircraft, scale=scale,
                      wind_ned_m_s=tuple(args.wind) if args.wind else (0.0, 0.0, 0.0),
                      gps_latency_s=args.gps_latency, gps_ashtech=args.gps_ashtech,
                      imu_seed=imu_seed,
                      faults=args.fault, vanish=args.vanish, thread_faults=args.thread_fault,
                      auto_switch_s=args.auto_switch, clock_steps=args.clock_step,
                      no_noise=args.no_noise, imu_profile=args.imu_profile,
                      gps_profile=args.gps_profile, turbulence=args.turbulence,
                      horizon_camera=args.horizon_camera,
                      level_calibration=not args.no_level_cal)


def _campaign(args: argparse.Namespace) -> int:
    """`--campaign SPEC`: fly (or resume) a campaign, or with --search run a parameter search,
    through the local pool or a Ray cluster (companion.sim.campaign)."""
    from datetime import UTC, datetime

    from companion.sim.campaign import CampaignError, load_campaign, run_campaign
    from companion.sim.campaign_state import output_uri
    from companion.sim.executors import ExecutorError
    from companion.sim.progress import CampaignProgress, final_table

    if args.jobs is not None and args.jobs < 1:
        print(f"companion sim: --jobs {args.jobs}: at least 1", file=sys.stderr)
        return 2
    try:
        if args.search:
            from companion.sim.search import load_search

            search = load_search(args.campaign)
            specs = []
        else:
            search = None
            specs = load_campaign(args.campaign)
    except CampaignError as exc:
        print(f"companion sim: --campaign {exc}", file=sys.stderr)
        return 2
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    out = output_uri(args.campaign_dir or Path("campaigns") / f"{args.campaign.stem}-{stamp}")
    try:
        executor = _executor(args)
    except ExecutorError as exc:
        print(f"companion sim: {exc}", file=sys.stderr)
        return 2
    found: dict[str, Any] | None = None
    stopped_by: list[int] = []
    try:
        with _stop_signals_interrupt(stopped_by):
            if search is not None:
                from companion.sim.search import run_search

                progress = CampaignProgress(search.trials, 0)
                try:
                    found = run_search(search, out, executor, storage=args.search_storage,
                                       events=progress.event)
                finally:
                    progress.close()
            else:
                progress = CampaignProgress(len(specs), 0)
                try:
                    result = run_campaign(specs, out, executor, spec_path=args.campaign,
                                          retry_failed=args.retry_failed, events=progress.event)
                finally:
                    progress.close()
    except KeyboardInterrupt:
        print(f"companion sim: campaign interrupted; run the same command again to fly the "
              f"rest ({out})", file=sys.stderr)
        return 128 + (stopped_by[0] if stopped_by else signal.SIGINT)
    except (CampaignError, ValueError) as exc:  # the campaign dir, the study's database
        print(f"companion sim: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the output cannot be written (a full disk, no permission)
        print(f"companion sim: --campaign-dir {out}: {exc}", file=sys.stderr)
        return 2
    finally:
        executor.close()  # before printing: Ray's executor holds stdout for its own lines
    if found is not None:
        print(json.dumps(found, indent=2) if args.json else
              f"search: best {found['metric']} = {found['best_value']} with "
              f"{found['best_params']} after {found['trials']} trials; {found['best_parm']}")
        return 0
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(final_table(result))
        print(f"campaign: {result['ok']}/{result['flights']} flights ok; {out}/campaign.json")
    return 0 if result["failed"] == 0 else 1


@contextlib.contextmanager
def _stop_signals_interrupt(stopped_by: list[int]) -> Iterator[None]:
    """SIGINT and SIGTERM raise KeyboardInterrupt in a campaign, whatever the process inherited.

    Started with SIGINT ignored (`cmd &` in a script or a CI job's background step: the shell
    ignores it for background commands, and Python keeps an inherited SIG_IGN), a campaign would
    fly on through `kill -INT`; a SIGTERM (systemd, `kill`) would end it at once, its flights
    killed with it and campaign.json not saying what was flown. Both now take the path of a
    Ctrl-C: the flights under way are stopped, the campaign's state is written, and the same
    command resumes it; a repeated signal is logged, not raised. `stopped_by` receives the signal
    (the exit code is 128 + it)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, _frame: object) -> None:
        if stopped_by:  # a repeat must not cut short the saving of what was flown
            log.warning("signal %s: the campaign is already stopping",
                        signal.Signals(signum).name)
            return
        stopped_by.append(signum)
        raise KeyboardInterrupt

    old = {s: signal.signal(s, interrupt) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)


def _executor(args: argparse.Namespace) -> Any:
    from companion.sim.executors import ExecutorError, LocalExecutor, RayExecutor

    if args.executor == "ray":
        return RayExecutor(args.ray_address, args.jobs, max_tries=args.max_tries)
    if args.ray_address:
        raise ExecutorError("--ray-address needs --executor ray")
    return LocalExecutor(args.jobs or max(1, os.cpu_count() or 1))


def _configured(args: argparse.Namespace, key: str) -> bool:
    """Whether the user set `key` in the configuration file or with --set."""
    if any(o.split("=", 1)[0].strip() == key for o in args.overrides):
        return True
    if args.config is None:
        return False
    import tomllib

    try:
        data = tomllib.loads(args.config.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError):
        return False
    section, _, name = key.partition(".")
    return name in data.get(section, {})


def _strip(argv: list[str], names: tuple[str, ...], *, takes_value: bool) -> list[str]:
    out: list[str] = []
    skip = False
    for a in argv:
        if skip:
            skip = False
            continue
        if a in names:
            skip = takes_value
            continue
        if any(a.startswith(n + "=") for n in names):
            continue
        out.append(a)
    return out


def add_commands(sub: argparse._SubParsersAction,
                 add_runtime_arguments: Callable[[argparse.ArgumentParser], None]) -> None:
    p = sub.add_parser("sim", help="fly a simulated aircraft (JSBSim) with every thread running")
    add_runtime_arguments(p)
    p.add_argument("--scenario", default="mixed",
                   help="level, turns, climb, aerobatic, mixed (default), auto")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seed-offset", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--imu-seed", type=int, metavar="N",
                   help="fly the IMU part of seed N whatever --seed is: its scale factors, "
                        "cross-axis terms, misalignment and temperature coefficients, with a "
                        "turn-on bias and noise of this flight's own (the same part switched on "
                        "again), e.g. to try the gyro calibration `companion estimation "
                        "calibration` took from its last flight")
    p.add_argument("--aircraft", default="c172p", help="JSBSim model: c172p (default) or j3cub")
    p.add_argument("--autopilot", choices=["arduplane"],
                   help="fly beside a real autopilot: ArduPilot's ArduPlane SITL, linked to the "
                        "companion as a TELEM cable (docs/autopilot.md); --speed is its speed-up")
    p.add_argument("--autopilot-binary", metavar="PATH",
                   help="the ArduPlane SITL program (default: $ARDUPILOT_SITL); nothing is "
                        "downloaded")
    p.add_argument("--autopilot-defaults", metavar="FILE",
                   help="ArduPilot's default parameter file for the model (default: plane.parm "
                        "beside the binary)")
    p.add_argument("--autopilot-mode", choices=["auto", "guided"], default="auto",
                   help="auto: the autopilot flies its circuit; guided: after the take-off, the "
                        "companion's control law flies through it (SET_ATTITUDE_TARGET)")
    p.add_argument("--vehicles", type=int, default=1, help="fly K aircraft (ids 1..K)")
    p.add_argument("--mavlink-port-step", type=int, default=0, metavar="N",
                   help="with --vehicles: aircraft i uses each UDP/TCP MAVLink endpoint's port "
                   "+ N*(i-1), one link per aircraft (a router's --master each); 0: all share")
    speed = p.add_mutually_exclusive_group()
    speed.add_argument("--realtime", action="store_true", help="real time (default)")
    speed.add_argument("--fast", action="store_true", help="5x faster than real time")
    speed.add_argument("--speed", type=float, help="any time scale, e.g. 2.5")
    p.add_argument("--campaign", type=Path, metavar="SPEC",
                   help="fly every flight of a campaign specification (TOML; docs/sitl.md)")
    p.add_argument("--jobs", type=int, default=None, metavar="J",
                   help="flights of a campaign flown at a time (default: one per core; with "
                        "--executor ray, the cluster's CPUs)")
    p.add_argument("--campaign-dir", metavar="DIR",
                   help="where a campaign's flights, state and dataset go: a path or a URI "
                        "pyarrow writes (s3://..., gs://...); default campaigns/<spec name>-<UTC "
                        "time>. The same directory again resumes the campaign")
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local: processes of this machine (default); ray: Ray tasks on a "
                        "cluster (pip install 'uav-companion[cluster]'; docs/campaigns.md)")
    p.add_argument("--ray-address", metavar="HOST:PORT",
                   help="the Ray cluster to join (default: start a local one)")
    p.add_argument("--max-tries", type=int, default=3, metavar="N",
                   help="with --executor ray: times a flight is sent again after its node was "
                        "lost, before it is recorded failed (default 3)")
    p.add_argument("--retry-failed", action="store_true",
                   help="resuming a campaign: fly again the flights recorded failed too")
    p.add_argument("--search", action="store_true",
                   help="the campaign's [search] table: an Optuna study of its parameters "
                        "(docs/campaigns.md)")
    p.add_argument("--search-storage", metavar="URL",
                   help="the study's database (default: SQLite file in the campaign dir)")
    speed.add_argument("--lockstep", action="store_true",
                       help="world and runtime in one process on simulated time, as fast as "
                            "the arithmetic; deterministic (no ground links: docs/sitl.md)")
    p.add_argument("--wind", type=float, nargs=3, metavar=("N", "E", "D"),
                   help="steady wind, m/s (NED: the direction it blows towards)")
    p.add_argument("--gps-latency", type=float, metavar="S",
                   help="mean age of a GPS epoch when it arrives (default: the GPS profile's; "
                   "the profile's jitter still applies)")
    p.add_argument("--imu-profile", metavar="NAME",
                   help="simulated IMU: consumer (default, MPU-6000 class), tactical "
                   "(ADIS16488A class), isis (the thesis's unit), simple (the original model), "
                   "ideal (docs/sitl.md)")
    p.add_argument("--gps-profile", metavar="NAME",
                   help="simulated receiver: ublox-m8 (default), dg16 (the thesis's Ashtech), "
                   "simple (the original model), ideal")
    p.add_argument("--turbulence", metavar="LEVEL",
                   help="JSBSim MIL-F-8785C turbulence: none, light, moderate (default; none "
                   "under --no-noise), severe")
    p.add_argument("--horizon-camera", default="off", metavar="LEVEL",
                   choices=("off", "clean", "light", "thesis"),
                   help="a forward camera for the horizon experiment: frames rendered at the "
                   "true attitude, disturbed as the thesis's video link (light, thesis) or "
                   "clean, through the real detector; its fixes reach the estimator as "
                   "HORIZON_ATTITUDE on the legacy command port (default off; docs/horizon.md)")
    p.add_argument("--gps-ashtech", action="store_true", help="add $PASHR,POS sentences")
    from companion.sim.faults import FAULT_KINDS

    for kind in FAULT_KINDS:  # the catalogue of SITL faults: one option each
        p.add_argument(kind.option, action="append", default=[], metavar=kind.syntax,
                       help=kind.help)
    p.add_argument("--auto-switch", type=float, default=20.0, metavar="S",
                   help="auto scenario: when the pilot engages automatic mode")
    p.add_argument("--no-noise", action="store_true",
                   help="perfect sensors: IMU and GPS without noise, bias, scale or mounting "
                   "error, vibration, latency jitter, multipath or outage; calm air unless "
                   "--turbulence is given")
    p.add_argument("--no-level-cal", action="store_true",
                   help="fly without the level calibration the simulated installation otherwise "
                   "gets before the flight (its trims set EST_TRIM_ROLL/PITCH)")
    p.set_defaults(func=cmd_sim, fast_exit=True)
