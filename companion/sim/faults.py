"""The catalogue of SITL faults: every kind, its option and syntax, its parser, where it applies.

A simulated flight can be faulted four ways, one row of `FAULT_KINDS` each:

* ``byte``, ``--fault``, applies in the world: `companion.sim.byte_faults.FaultInjector` alters
  a device's bytes;
* ``vanish``, ``--vanish``, applies in the world: it closes a device's port and opens it again;
* ``thread``, ``--thread-fault``, applies in the runtime: `companion.sim.thread_faults`
  makes one of its threads misbehave;
* ``clock``, ``--clock-step``, applies to the clock: `companion.sim.clock_faults` steps the
  runtime process's wall clock.

``world`` faults are applied by the world (its own process, or the world task of a lockstep
flight) and reach the world process on its command line; ``runtime`` and ``clock`` ones are
applied in the runtime's process. `companion sim`'s options and their help, the checks made
before a flight, the world process's options and the runner's launch line all come from the
table, so a new kind is one row here, one parser and its mechanism.

This module owns what a fault *is*: its parsed form (`FaultPlan`, `Vanish`, `ThreadFault`, a
clock step) and the parser from its text; each mechanism's module owns how it is applied. It
imports nothing heavy: `companion --help` reads the table.

The devices a fault may name are the thesis aircraft's (`companion.sim.ports.DEVICES`) and the
ones whose row of the vehicle's table brings a simulator (`companion.sim.plugins`), so a
plug-in device can be faulted too.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from companion.sim.ports import DEVICES

__all__ = ["FAULT_KINDS", "THREAD_FAULT_KINDS", "FaultKind", "FaultPlan", "ThreadFault", "Vanish",
           "fault_devices", "parse_clock_step", "parse_fault", "parse_thread_fault",
           "parse_vanish", "world_faults"]

THREAD_FAULT_KINDS = ("raise", "crash-loop", "pyloop", "cblock", "alloc")
"""What `--thread-fault` makes a thread do (`companion.sim.thread_faults` says what each is)."""


def fault_devices() -> tuple[str, ...]:
    """The devices a fault may name: the thesis devices, then every device the vehicle's table
    gives a simulator."""
    from companion.sim.plugins import simulated_devices

    return (*DEVICES, *simulated_devices())


# ---------------------------------------------------------------------------------------------
# byte faults (`--fault`)


@dataclass(frozen=True, slots=True)
class FaultPlan:
    """Faults to inject into a device's byte stream, chunk by chunk (a chunk = one frame/epoch)."""

    silence_s: tuple[tuple[float, float], ...] = ()
    """Windows [start, end) of sim time during which the device sends nothing."""
    garbage_prob: float = 0.0
    """Chance that random bytes precede a chunk."""
    garbage_len: tuple[int, int] = (1, 16)
    """Inclusive length range of a garbage burst."""
    cut_prob: float = 0.0
    """Chance that a chunk is cut short (its tail never sent)."""
    bad_checksum_prob: float = 0.0
    """Chance that one byte of a chunk (past its first two, before a trailing CR/LF) is altered,
    so its checksum no longer matches."""
    flood_s: tuple[tuple[float, float], ...] = ()
    """Windows [start, end) of sim time during which every chunk is sent `flood_factor` times:
    a babbling device, `flood_factor` times its byte rate, every copy valid."""
    flood_factor: int = 10
    wrong_baud_s: tuple[tuple[float, float], ...] = ()
    """Windows [start, end) during which the device sends at `baud_ratio` times the baud rate
    the computer's UART expects, so the computer receives what a mismatched UART makes of the
    bytes (see :func:`uart_misread`)."""
    baud_ratio: float = 2.0
    utc_step_s: tuple[tuple[float, float], ...] = ()
    """(at sim time, seconds) steps of the device's own clock: the GPS receiver's UTC jumps
    (a receiver reset, a leap second, a week-number rollover) while its fixes stay right."""

    def __post_init__(self) -> None:
        for name in ("garbage_prob", "cut_prob", "bad_checksum_prob"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"FaultPlan.{name} must be within 0..1, got {value}")
        if not 2 <= self.flood_factor <= 100:
            raise ValueError(f"FaultPlan.flood_factor must be within 2..100, got {self.flood_factor}")
        if not (0.05 <= self.baud_ratio <= 20.0) or abs(self.baud_ratio - 1.0) < 0.02:
            raise ValueError(f"FaultPlan.baud_ratio must be within 0.05..20 and not 1, got "
                             f"{self.baud_ratio}")
        for what, windows in (("flood_s", self.flood_s), ("wrong_baud_s", self.wrong_baud_s)):
            for start, end in windows:
                if not start <= end:
                    raise ValueError(f"FaultPlan.{what} window ({start}, {end}) ends before it "
                                     "starts")
        low, high = self.garbage_len
        if not 1 <= low <= high <= 4096:
            raise ValueError(
                f"FaultPlan.garbage_len must satisfy 1 <= min <= max <= 4096, got {self.garbage_len}"
            )
        for start, end in self.silence_s:
            if not start <= end:
                raise ValueError(
                    f"FaultPlan.silence_s window ({start}, {end}) ends before it starts"
                )


def parse_fault(text: str, devices: Sequence[str] | None = None) -> tuple[str, FaultPlan]:
    """`DEV:key=value,...`: garbage, cut, badsum (probabilities); silence, flood, wrongbaud
    (START-END windows, repeatable); floodx (copies per chunk, default 10); baudratio (the
    device's baud rate over the expected one, default 2); utcstep=AT:SECONDS (GPS only).
    `devices`: the devices it may name (default `fault_devices()`)."""
    if devices is None:
        devices = fault_devices()
    dev, _, spec = text.partition(":")
    if dev not in devices:
        raise ValueError(f"--fault {text!r}: device must be one of {', '.join(devices)}")
    kwargs: dict[str, Any] = {}
    windows: dict[str, list[tuple[float, float]]] = {"silence": [], "flood": [], "wrongbaud": []}
    steps: list[tuple[float, float]] = []
    for item in filter(None, spec.split(",")):
        key, _, value = item.partition("=")
        try:
            _fault_item(dev, key, value, kwargs, windows, steps)
        except ValueError as exc:
            raise ValueError(f"--fault {text!r}: {item!r}: {exc}") from None
    try:
        return dev, FaultPlan(silence_s=tuple(windows["silence"]),
                              flood_s=tuple(windows["flood"]),
                              wrong_baud_s=tuple(windows["wrongbaud"]), utc_step_s=tuple(steps),
                              **kwargs)
    except ValueError as exc:
        raise ValueError(f"--fault {text!r}: {exc}") from None


def _fault_item(dev: str, key: str, value: str, kwargs: dict[str, Any],
                windows: dict[str, list[tuple[float, float]]],
                steps: list[tuple[float, float]]) -> None:
    if key == "garbage":
        kwargs["garbage_prob"] = float(value)
    elif key == "cut":
        kwargs["cut_prob"] = float(value)
    elif key == "badsum":
        kwargs["bad_checksum_prob"] = float(value)
    elif key in ("silence", "flood", "wrongbaud"):
        a, _, b = value.partition("-")
        windows[key].append((float(a), float(b)))
    elif key == "floodx":
        kwargs["flood_factor"] = int(value)
    elif key == "baudratio":
        kwargs["baud_ratio"] = float(value)
    elif key == "utcstep" and dev == "gps":
        at, _, delta = value.partition(":")
        steps.append((float(at), float(delta)))
    else:
        raise ValueError(f"unknown key {key!r} (garbage, cut, badsum, "
                         "silence, flood, floodx, wrongbaud, baudratio, utcstep for gps)")


# ---------------------------------------------------------------------------------------------
# vanishing ports (`--vanish`)


@dataclass
class Vanish:
    """A port that disappears at `start_s` (sim time) and returns `duration_s` later."""

    device: str
    start_s: float
    duration_s: float
    renamed: bool = False
    """Return under another kernel name (/dev/pts/N), as a USB adapter re-enumerated as
    ttyUSB1 after ttyUSB0; the stable link follows it."""
    done: bool = False
    gone: bool = False


def parse_vanish(text: str, devices: Sequence[str] | None = None) -> Vanish:
    """`DEV:START:DURATION[:renamed]` in sim seconds; `devices` as for `parse_fault`."""
    if devices is None:
        devices = fault_devices()
    try:
        dev, start, duration, *rest = text.split(":")
        if dev not in devices or rest not in ([], ["renamed"]):
            raise ValueError
        return Vanish(dev, float(start), float(duration), renamed=bool(rest))
    except ValueError:
        raise ValueError(f"--vanish {text!r}: expected DEV:START_S:DURATION_S[:renamed]") from None


# ---------------------------------------------------------------------------------------------
# thread faults (`--thread-fault`)


@dataclass(frozen=True)
class ThreadFault:
    thread: str
    kind: str
    at_s: float
    """Flight-clock seconds after the runtime started."""


def parse_thread_fault(text: str) -> ThreadFault:
    """`THREAD:KIND:AT_S`, e.g. `estimator:raise:20`."""
    parts = text.split(":")
    if len(parts) != 3 or parts[1] not in THREAD_FAULT_KINDS:
        raise ValueError(f"--thread-fault {text!r}: expected THREAD:KIND:AT_S with KIND one of "
                         f"{', '.join(THREAD_FAULT_KINDS)}")
    try:
        at_s = float(parts[2])
    except ValueError:
        raise ValueError(f"--thread-fault {text!r}: AT_S must be a number of seconds") from None
    return ThreadFault(parts[0], parts[1], at_s)


# ---------------------------------------------------------------------------------------------
# wall-clock steps (`--clock-step`)


def parse_clock_step(text: str) -> tuple[float, float]:
    """`AT_S:STEP_S`: at flight time AT_S (s), the wall clock moves by STEP_S (s, signed)."""
    try:
        at, step = (float(v) for v in text.split(":"))
    except ValueError:
        raise ValueError(f"--clock-step {text!r}: expected AT_S:STEP_S, e.g. 20:3600") from None
    if at < 0:
        raise ValueError(f"--clock-step {text!r}: AT_S must not be negative")
    return at, step


# ---------------------------------------------------------------------------------------------
# the catalogue


@dataclass(frozen=True)
class FaultKind:
    """One kind of fault: how it is asked for and where it is applied."""

    name: str
    option: str
    """The `companion sim` option, repeatable (and the world process's, for ``world`` ones)."""
    syntax: str
    """The option's value, as its help shows it."""
    help: str
    """What it does, as `companion sim --help` says it."""
    parse: Callable[[str], Any]
    """Text to its parsed form; a ValueError names the option and the text."""
    applies: str
    """``world``: by the world, on a device's bytes or port; ``runtime``: in the runtime's
    threads; ``clock``: to the runtime process's wall clock."""
    key: str
    """The `companion.sim.runner.SimOptions` field (and campaign key) holding its texts."""

    @property
    def dest(self) -> str:
        """The option's attribute in parsed arguments (``--thread-fault`` -> ``thread_fault``)."""
        return self.option[2:].replace("-", "_")


FAULT_KINDS: tuple[FaultKind, ...] = (
    FaultKind("byte", "--fault", "DEV:SPEC",
              "inject device faults, e.g. imu:garbage=0.01,cut=0.01,badsum=0.01,"
              "silence=30-32; also flood=A-B (floodx=10 copies), wrongbaud=A-B "
              "(baudratio=2), gps:utcstep=AT:SECONDS (docs/sitl.md)",
              parse_fault, "world", "faults"),
    FaultKind("vanish", "--vanish", "DEV:START:DURATION",
              "make a device's port disappear and return; DEV:START:DURATION:renamed "
              "returns it under another kernel name behind the same stable link",
              parse_vanish, "world", "vanish"),
    FaultKind("thread", "--thread-fault", "THREAD:KIND:AT_S",
              "inject a fault into a runtime thread at a flight time: KIND is "
              f"{', '.join(THREAD_FAULT_KINDS[:-1])} or {THREAD_FAULT_KINDS[-1]} "
              "(e.g. estimator:raise:20)",
              parse_thread_fault, "runtime", "thread_faults"),
    FaultKind("clock", "--clock-step", "AT_S:STEP_S",
              "step the runtime process's wall clock by STEP_S s at flight time AT_S "
              "(as NTP or GPS time does in flight), e.g. 20:3600",
              parse_clock_step, "clock", "clock_steps"),
)


def world_faults() -> tuple[FaultKind, ...]:
    """The kinds the world applies: the world process takes them on its command line."""
    return tuple(kind for kind in FAULT_KINDS if kind.applies == "world")
