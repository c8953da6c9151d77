"""Typed parameter registry: declaration, validation, change notification and persistence.

Parameters are declared next to the code that owns them (`ParamSpec`), the way ArduPilot's
`AP_GROUPINFO` and PX4's `module.yaml` do, so the documentation, the MAVLink parameter protocol,
the legacy protocol and the parameter files all come from one table.

Only two types exist, int32 and float32, because those are the only ones every MAVLink ground
station (MAVSDK in particular) handles reliably.
"""

from __future__ import annotations

import decimal
import enum
import logging
import math
import numbers
import re
import struct
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.core.files import atomic_write_text

log = logging.getLogger(__name__)

NAME_RE = re.compile(r"^[A-Z][A-Z0-9]*_[A-Z0-9_]+$")
MAX_NAME_LEN = 16
INT32_MIN, INT32_MAX = -(2**31), 2**31 - 1

# MAV_PARAM_TYPE values, used by the QGroundControl .params format and the MAVLink bridge.
MAV_PARAM_TYPE_INT32 = 6
MAV_PARAM_TYPE_REAL32 = 9


class ParamType(enum.Enum):
    INT32 = "int32"
    FLOAT32 = "float32"

    @property
    def mav_type(self) -> int:
        return MAV_PARAM_TYPE_INT32 if self is ParamType.INT32 else MAV_PARAM_TYPE_REAL32


ParamValue = int | float


_FLOAT32 = struct.Struct("<f")


def to_float32(value: float) -> float:
    """Round a Python float to the nearest float32, the precision the parameter really has
    (as numpy's cast does; done with `struct` so that reading parameters imports no numpy)."""
    try:
        result: float = _FLOAT32.unpack(_FLOAT32.pack(value))[0]
    except OverflowError:  # finite but beyond float32: numpy's cast gives infinity too
        return math.copysign(math.inf, value)
    return result


def format_value(ptype: ParamType, value: ParamValue) -> str:
    """Shortest text that reads back to the same int32 / float32, positional, trailing zeros
    trimmed (what numpy's ``format_float_positional(unique=True, trim="-")`` prints)."""
    if ptype is ParamType.INT32:
        return str(int(value))
    v = to_float32(float(value))
    if not math.isfinite(v):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
    text = repr(v)
    for digits in range(1, 10):  # nine significant digits always read back a float32
        text = f"{v:.{digits}g}"
        if to_float32(float(text)) == v:
            break
    positional = format(decimal.Decimal(text), "f")
    if "." in positional:
        positional = positional.rstrip("0").rstrip(".")
    return positional


@dataclass(frozen=True)
class ParamSpec:
    """One parameter's metadata; `default`, `min` and `max` are in `unit`."""

    name: str
    ptype: ParamType
    default: ParamValue
    min: ParamValue
    max: ParamValue
    unit: str = ""
    description: str = ""
    read_only: bool = False
    reboot_required: bool = False

    def __post_init__(self) -> None:
        if len(self.name) > MAX_NAME_LEN or not NAME_RE.match(self.name):
            raise ValueError(
                f"parameter name {self.name!r} must be GROUP_NAME, upper case, "
                f"at most {MAX_NAME_LEN} characters"
            )
        if not (self.min <= self.default <= self.max):
            raise ValueError(
                f"parameter {self.name}: default {self.default} outside [{self.min}, {self.max}]"
            )
        if self.ptype is ParamType.INT32:
            for v in (self.default, self.min, self.max):
                if int(v) != v or not INT32_MIN <= v <= INT32_MAX:
                    raise ValueError(f"parameter {self.name}: {v} is not an int32")
        else:
            # a value has one form whatever its source: the float32 it is stored and sent as.
            # A default kept as the Python float it was written as (0.015) would differ from
            # the same value read back from a parameter file or a ground station
            # (0.015000001), and a flight on defaults from one on a saved file.
            for attr in ("default", "min", "max"):
                object.__setattr__(self, attr, to_float32(float(getattr(self, attr))))

    @property
    def group(self) -> str:
        return self.name.split("_", 1)[0]

    def validate(self, value: object) -> ParamValue:
        """Coerce `value` to this parameter's type or raise `ParamError` saying why not."""
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise ParamError(self.name, f"wrong type: expected {self.ptype.value}, got {value!r}",
                             ParamErrorKind.WRONG_TYPE)
        v = float(value)
        if math.isnan(v) or math.isinf(v):
            raise ParamError(self.name, f"value {value!r} is not finite")
        coerced: ParamValue
        if self.ptype is ParamType.INT32:
            if v != int(v):
                raise ParamError(self.name, f"wrong type: {value!r} is not an integer (int32)",
                                 ParamErrorKind.WRONG_TYPE)
            coerced = int(v)
        else:
            coerced = to_float32(v)
        lo, hi = self.min, self.max
        if self.ptype is ParamType.FLOAT32:
            lo, hi = to_float32(lo), to_float32(hi)
        if not lo <= coerced <= hi:
            raise ParamError(
                self.name,
                f"out of range: {format_value(self.ptype, coerced)} not in "
                f"[{format_value(self.ptype, lo)}, {format_value(self.ptype, hi)}]"
                + (f" {self.unit}" if self.unit else ""),
            )
        return coerced


class ParamErrorKind(enum.Enum):
    """Why a parameter operation was refused, for callers that answer in a protocol's own terms
    (a MAVLink PARAM_ERROR code, a legacy ACK result) without parsing the reason text."""

    UNKNOWN = "unknown"
    READ_ONLY = "read-only"
    WRONG_TYPE = "wrong type"
    OUT_OF_RANGE = "out of range"
    CONFLICT = "conflict"
    """Refused by a rule between parameters (see `ParamRegistry.add_rule`)."""


class ParamError(ValueError):
    """A refused parameter operation; `reason` is short enough for a MAVLink STATUSTEXT."""

    def __init__(self, name: str, reason: str,
                 kind: ParamErrorKind = ParamErrorKind.OUT_OF_RANGE) -> None:
        super().__init__(f"{name}: {reason}")
        self.name = name
        self.reason = reason
        self.kind = kind


Rule = Callable[[str, "ParamValue", Callable[[str], "ParamValue"]], "str | None"]
"""A rule between parameters: ``rule(name, new_value, value_of)`` returns why the change is
refused, or None. `value_of` gives the other parameters' values as they would be after the
change (so a rule sees every value of a multi-parameter request)."""


def int_param(name: str, default: int, lo: int, hi: int, unit: str = "", desc: str = "",
              *, read_only: bool = False, reboot: bool = False) -> ParamSpec:
    return ParamSpec(name, ParamType.INT32, default, lo, hi, unit, desc, read_only, reboot)


def float_param(name: str, default: float, lo: float, hi: float, unit: str = "", desc: str = "",
                *, read_only: bool = False, reboot: bool = False) -> ParamSpec:
    return ParamSpec(name, ParamType.FLOAT32, default, lo, hi, unit, desc, read_only, reboot)


@dataclass(frozen=True)
class FileIssue:
    """A line of a parameter file that could not be applied, and why."""

    path: str
    line: int
    text: str
    reason: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.reason}: {self.text.strip()!r}"


Listener = Callable[[str, ParamValue], None]


class ParamRegistry:
    """All parameters of one vehicle, in declaration order (which gives the MAVLink index).

    Thread-safe: the lock covers dictionary access only. Listeners run in the setter's thread
    after the lock is released and must be cheap (set a flag, post to a queue).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._specs: dict[str, ParamSpec] = {}
        self._order: list[str] = []
        self._values: dict[str, ParamValue] = {}
        self._listeners: list[Listener] = []
        self._rules: list[Rule] = []
        self._generation = 0
        self._saved_generation = 0
        self._path: Path | None = None

    # -- declaration -------------------------------------------------------------------------
    def declare(self, spec: ParamSpec) -> None:
        with self._lock:
            old = self._specs.get(spec.name)
            if old is not None:
                if old != spec:
                    raise ValueError(f"parameter {spec.name} declared twice with different metadata")
                return
            self._specs[spec.name] = spec
            self._order.append(spec.name)
            self._values[spec.name] = spec.default

    def declare_all(self, specs: Iterable[ParamSpec]) -> None:
        for spec in specs:
            self.declare(spec)

    # -- access ------------------------------------------------------------------------------
    def __contains__(self, name: object) -> bool:
        with self._lock:
            return name in self._specs

    def __len__(self) -> int:
        with self._lock:
            return len(self._order)

    def __iter__(self) -> Iterator[ParamSpec]:
        return iter(self.specs())

    def specs(self) -> list[ParamSpec]:
        with self._lock:
            return [self._specs[n] for n in self._order]

    def spec(self, name: str) -> ParamSpec:
        with self._lock:
            try:
                return self._specs[name]
            except KeyError:
                raise ParamError(name, "unknown parameter", ParamErrorKind.UNKNOWN) from None

    def index_of(self, name: str) -> int:
        with self._lock:
            try:
                return self._order.index(name)
            except ValueError:
                raise ParamError(name, "unknown parameter", ParamErrorKind.UNKNOWN) from None

    def name_at(self, index: int) -> str:
        with self._lock:
            if not 0 <= index < len(self._order):
                raise ParamError(f"#{index}", f"index out of range 0..{len(self._order) - 1}")
            return self._order[index]

    def get(self, name: str) -> ParamValue:
        with self._lock:
            try:
                return self._values[name]
            except KeyError:
                raise ParamError(name, "unknown parameter", ParamErrorKind.UNKNOWN) from None

    def snapshot(self) -> dict[str, ParamValue]:
        with self._lock:
            return {n: self._values[n] for n in self._order}

    # -- change ------------------------------------------------------------------------------
    def add_rule(self, rule: Rule) -> Callable[[], None]:
        """Register a rule between parameters, checked on every change from any source (MAVLink,
        the legacy protocol, a file, the console); returns a function that removes it."""
        return self._register(self._rules, rule)

    def _register(self, items: list[Any], item: Any) -> Callable[[], None]:
        """Append `item` under the lock; the returned function removes it (idempotent)."""
        with self._lock:
            items.append(item)

        def remove() -> None:
            with self._lock:
                if item in items:
                    items.remove(item)

        return remove

    def check(self, changes: Mapping[str, object], *, force: bool = False) -> dict[str, ParamValue]:
        """Validate a request of one or more changes without applying it: each value against
        its parameter, then every rule against the values as they would be afterwards.

        Returns the coerced values; raises the first `ParamError` (with its `kind`)."""
        coerced: dict[str, ParamValue] = {}
        for name, value in changes.items():
            spec = self.spec(name)
            if spec.read_only and not force:
                raise ParamError(name, "read-only", ParamErrorKind.READ_ONLY)
            coerced[name] = spec.validate(value)
        with self._lock:
            rules = list(self._rules)

        def value_of(other: str) -> ParamValue:
            return coerced[other] if other in coerced else self.get(other)

        for name, value in coerced.items():
            for rule in rules:
                reason = rule(name, value, value_of)
                if reason:
                    raise ParamError(name, reason, ParamErrorKind.CONFLICT)
        return coerced

    def set(self, name: str, value: object, *, force: bool = False) -> ParamValue:
        """Validate and apply one change; raises ParamError (see `check`).

        `force` lets the owner change a read-only value (for example a measured figure).
        """
        return self.set_many({name: value}, force=force)[name]

    def set_many(self, changes: Mapping[str, object], *,
                 force: bool = False) -> dict[str, ParamValue]:
        """Apply every change of one request or none of them (see `check`): the one way a
        parameter changes, whoever asks."""
        coerced = self.check(changes, force=force)
        changed: list[tuple[str, ParamValue]] = []
        with self._lock:
            for name, value in coerced.items():
                if self._values[name] != value:
                    self._values[name] = value
                    self._generation += 1
                    changed.append((name, value))
            listeners = list(self._listeners)
        for name, value in changed:
            for listener in listeners:
                try:
                    listener(name, value)
                except Exception:  # a listener's bug must not refuse a valid change
                    log.exception("parameter listener failed for %s", name)
        return coerced

    def subscribe(self, listener: Listener) -> Callable[[], None]:
        """Call `listener(name, value)` after every change; returns an unsubscribe function."""
        return self._register(self._listeners, listener)

    # -- persistence -------------------------------------------------------------------------
    def attach_file(self, path: Path) -> list[FileIssue]:
        """Load `path` if it exists and keep it as the place changes are persisted to.

        Bad lines are reported and left at their defaults; the rest still applies, because a
        damaged file must never keep the aircraft from starting.
        """
        self._path = Path(path)
        issues: list[FileIssue] = []
        if self._path.exists():
            issues = self.load(self._path)
        with self._lock:
            self._saved_generation = self._generation
        return issues

    @property
    def path(self) -> Path | None:
        return self._path

    @property
    def dirty(self) -> bool:
        with self._lock:
            return self._generation != self._saved_generation

    def load(self, path: Path) -> list[FileIssue]:
        """Apply a QGroundControl `.params` or MAVProxy `.parm` file; return the lines refused."""
        issues: list[FileIssue] = []
        for lineno, name, text, value, problem in parse_param_file(path):
            if problem is not None:
                issues.append(FileIssue(str(path), lineno, text, problem))
                continue
            assert name is not None
            if name in self and self.spec(name).read_only:
                # read-only values come from the configuration or the code, never from a file
                # that anyone (or an earlier attacker's PARAM_SET) may have written
                continue
            try:
                self.set(name, value)
            except ParamError as exc:
                issues.append(FileIssue(str(path), lineno, text, exc.reason))
        for issue in issues:
            log.warning("parameter file: %s (default kept)", issue)
        return issues

    def flush(self) -> bool:
        """Persist to the attached file if anything changed since the last save; True if saved."""
        with self._lock:
            if self._path is None or self._generation == self._saved_generation:
                return False
            generation = self._generation
        self.save(self._path)
        with self._lock:
            self._saved_generation = max(self._saved_generation, generation)
        return True

    def save(self, path: Path, *, fmt: str = "parm", sysid: int = 1, compid: int = 1) -> None:
        """Write atomically (temp file, fsync, rename, fsync dir): a crash leaves old or new."""
        text = self.render(fmt, sysid=sysid, compid=compid)
        atomic_write_text(Path(path), text)

    def render(self, fmt: str = "parm", *, sysid: int = 1, compid: int = 1) -> str:
        snapshot = self.snapshot()
        specs = {s.name: s for s in self.specs()}
        lines: list[str] = []
        if fmt == "parm":
            lines.append("# MAVProxy-style parameter file: NAME VALUE")
            for name, value in snapshot.items():
                lines.append(f"{name:<16} {format_value(specs[name].ptype, value)}")
        elif fmt == "params":
            lines.append(f"# Onboard parameters for Vehicle {sysid}")
            lines.append("#")
            lines.append("# Vehicle-Id Component-Id Name Value Type")
            for name, value in snapshot.items():
                spec = specs[name]
                lines.append(
                    f"{sysid}\t{compid}\t{name}\t{format_value(spec.ptype, value)}\t{spec.ptype.mav_type}"
                )
        else:
            raise ValueError(f"unknown parameter file format {fmt!r} (use 'parm' or 'params')")
        return "\n".join(lines) + "\n"


def parse_param_file(
    path: Path,
) -> Iterator[tuple[int, str | None, str, float, str | None]]:
    """Yield (line number, name, raw line, value, problem) for each non-comment line.

    Accepts both the QGroundControl layout (`sysid compid NAME VALUE TYPE`, tab separated) and the
    MAVProxy layout (`NAME VALUE`, spaces or a comma); the format is decided per line so a
    hand-edited mixture still loads.
    """
    try:
        raw = Path(path).read_bytes()
    except OSError as exc:
        yield 0, None, "", 0.0, f"cannot read file: {exc.strerror}"
        return
    for lineno, bline in enumerate(raw.split(b"\n"), start=1):
        try:
            line = bline.decode("utf-8")
        except UnicodeDecodeError as exc:
            yield lineno, None, repr(bline[:40]), 0.0, f"not UTF-8 text (byte {exc.start})"
            continue
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = re.split(r"[\s,]+", stripped)
        if len(fields) == 5:
            name, value_text = fields[2], fields[3]
        elif len(fields) == 2:
            name, value_text = fields[0], fields[1]
        else:
            yield lineno, None, line, 0.0, f"expected 'NAME VALUE' or 5 QGC columns, got {len(fields)} fields"
            continue
        try:
            value = float(value_text)
        except ValueError:
            yield lineno, None, line, 0.0, f"value {value_text!r} of {name} is not a number"
            continue
        yield lineno, name, line, value, None



