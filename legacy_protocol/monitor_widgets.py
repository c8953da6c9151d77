"""Widgets of the legacy ground monitor: status LEDs, the confirm dialog, a thread's row, data pages.

Each widget draws one part of a vehicle's state (:class:`~legacy_protocol.monitor_link.VehicleState`)
and knows nothing of the link or the commands; :mod:`legacy_protocol.monitor_app` lays them out,
drains the link and sends the commands. Kept apart so the app reads as the station's behaviour
and these as its display.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

from textual.app import ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual.screen import ModalScreen
from textual.widgets import (
    Button,
    Input,
    Label,
    ProgressBar,
    Sparkline,
    Static,
)

from legacy_protocol.messages import (
    UNCHANGED,
    GpsFix,
    Servo,
    ServoFlag,
    ThreadFlag,
    ThreadStatus,
)
from legacy_protocol.monitor_link import (
    VehicleKey,
    VehicleState,
)

__all__ = [
    "CONTROL_ROWS",
    "ESTIMATOR_ROWS",
    "GPS_ROWS",
    "IMU_ROWS",
    "ConfirmScreen",
    "DataPage",
    "Led",
    "ServoPage",
    "ThreadRow",
    "parse_param",
    "set_text",
]

_DEG_PER_RAD = 180.0 / math.pi
_LED_NAMES = ("init", "run", "loop", "alive")
_LED_FLAGS = (ThreadFlag.INITIALISED, ThreadFlag.RUNNING, ThreadFlag.IN_PERIODIC, ThreadFlag.ALIVE)
_SERVO_MIN_US = 1000
_SERVO_SPAN_US = 1000


def _num(fmt: str, scale: float | None = None) -> Callable[[Any], str]:
    if scale is None:
        return lambda v: format(v, fmt)
    return lambda v: format(v * scale, fmt)


def _fix(v: Any) -> str:
    try:
        return GpsFix(v).name
    except ValueError:
        return f"unknown ({v})"


@dataclass(frozen=True)
class _Row:
    """One displayed field: label, message attribute, unit, formatter, sparkline or not."""

    label: str
    attr: str
    unit: str
    fmt: Callable[[Any], str]
    scale: float = 1.0
    spark: bool = False


IMU_ROWS = (
    _Row("roll rate p", "p_rad_s", "deg/s", _num("+8.2f", _DEG_PER_RAD), _DEG_PER_RAD, True),
    _Row("pitch rate q", "q_rad_s", "deg/s", _num("+8.2f", _DEG_PER_RAD), _DEG_PER_RAD, True),
    _Row("yaw rate r", "r_rad_s", "deg/s", _num("+8.2f", _DEG_PER_RAD), _DEG_PER_RAD, True),
    _Row("accel x", "ax_m_s2", "m/s²", _num("+8.3f"), spark=True),
    _Row("accel y", "ay_m_s2", "m/s²", _num("+8.3f"), spark=True),
    _Row("accel z", "az_m_s2", "m/s²", _num("+8.3f"), spark=True),
    _Row("temperature", "temperature_c", "°C", _num("8.1f"), spark=True),
    _Row("frame count", "frame_count", "", _num("8d")),
)
GPS_ROWS = (
    _Row("latitude", "lat_deg", "deg", _num("+.7f")),
    _Row("longitude", "lon_deg", "deg", _num("+.7f")),
    _Row("altitude", "alt_m", "m", _num("8.1f"), spark=True),
    _Row("v north", "v_north_m_s", "m/s", _num("+8.2f"), spark=True),
    _Row("v east", "v_east_m_s", "m/s", _num("+8.2f"), spark=True),
    _Row("v down", "v_down_m_s", "m/s", _num("+8.2f"), spark=True),
    _Row("fix", "fix_type", "", _fix),
    _Row("satellites", "satellites", "", _num("d"), spark=True),
    _Row("PDOP", "pdop", "", _num("6.2f")),
    _Row("HDOP", "hdop", "", _num("6.2f"), spark=True),
    _Row("VDOP", "vdop", "", _num("6.2f")),
    _Row("TDOP", "tdop", "", _num("6.2f")),
    _Row("latency", "latency_ms", "ms", _num("6.1f")),
    _Row("altitude std", "alt_std_m", "m", _num("6.2f")),
)
ESTIMATOR_ROWS = (
    _Row("roll", "roll_rad", "deg", _num("+8.2f", _DEG_PER_RAD), _DEG_PER_RAD, True),
    _Row("pitch", "pitch_rad", "deg", _num("+8.2f", _DEG_PER_RAD), _DEG_PER_RAD, True),
    _Row("yaw", "yaw_rad", "deg", _num("+8.2f", _DEG_PER_RAD), _DEG_PER_RAD, True),
    _Row("north", "north_m", "m", _num("+9.1f"), spark=True),
    _Row("east", "east_m", "m", _num("+9.1f"), spark=True),
    _Row("down", "down_m", "m", _num("+9.1f"), spark=True),
    _Row("v north", "v_north_m_s", "m/s", _num("+8.2f")),
    _Row("v east", "v_east_m_s", "m/s", _num("+8.2f")),
    _Row("v down", "v_down_m_s", "m/s", _num("+8.2f")),
    _Row("gyro bias x", "gyro_bias_x_rad_s", "rad/s", _num("+.5f")),
    _Row("gyro bias y", "gyro_bias_y_rad_s", "rad/s", _num("+.5f")),
    _Row("gyro bias z", "gyro_bias_z_rad_s", "rad/s", _num("+.5f")),
)
CONTROL_ROWS = (
    _Row("aileron", "aileron", "", _num("+6.3f"), spark=True),
    _Row("elevator", "elevator", "", _num("+6.3f"), spark=True),
    _Row("rudder", "rudder", "", _num("+6.3f"), spark=True),
    _Row("throttle", "throttle", "", _num("6.3f"), spark=True),
    _Row("enabled", "enabled", "", lambda v: "yes" if v else "no"),
)


def set_text(widget: Static, text: str) -> None:
    """Update only on change: redrawing identical text every tick wastes a shared CPU."""
    if str(widget.content) != text:
        widget.update(text)


class Led(Static):
    """A status lamp: filled and green when lit, hollow and dim when not (or unknown)."""

    def __init__(self, name: str, *, lit: bool | None = None, id: str | None = None) -> None:
        super().__init__(
            f"{'●' if lit else '○'} {name}",
            id=id,
            classes="led on" if lit else "led off",
            markup=False,
        )
        self._label = name
        self.lit = lit

    def set(self, lit: bool | None) -> None:
        if lit == self.lit:
            return
        self.lit = lit
        self.set_class(bool(lit), "on")
        self.set_class(not lit, "off")
        self.update(f"{'●' if lit else '○'} {self._label}")


class ConfirmScreen(ModalScreen[bool]):
    """Yes/no dialog guarding commands that cannot be undone from the ground."""

    BINDINGS: ClassVar = [Binding("escape", "cancel", "Cancel")]

    def __init__(self, question: str, confirm_label: str = "Yes") -> None:
        super().__init__()
        self._question = question
        self._confirm_label = confirm_label

    def compose(self) -> ComposeResult:
        with Vertical(id="dialog"):
            yield Label(self._question, id="question")
            with Horizontal(id="dialog-buttons"):
                yield Button(self._confirm_label, variant="error", id="confirm")
                yield Button("Cancel", variant="primary", id="cancel")

    def on_mount(self) -> None:
        self.query_one("#cancel", Button).focus()

    def on_button_pressed(self, event: Button.Pressed) -> None:
        event.stop()  # the answer is ours; the app's own button handler must not see it
        self.dismiss(event.button.id == "confirm")

    def action_cancel(self) -> None:
        self.dismiss(False)


def parse_param(text: str, what: str, *, allow_zero: bool = False) -> int:
    """Input text to a wire value: blank keeps the aircraft's value (UNCHANGED)."""
    text = text.strip()
    if not text:
        return UNCHANGED
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"{what}: '{text}' is not a whole number") from None
    low = 0 if allow_zero else 1
    if not low <= value < UNCHANGED:
        raise ValueError(f"{what}: {value} outside {low}..{UNCHANGED - 1}")
    return value


def _thread_title(status: ThreadStatus) -> str:
    return f"{status.thread_id} {status.name or 'thread'}"


def _thread_stats(status: ThreadStatus, age_s: float) -> str:
    return (
        f"restarts {status.restarts:3d} · mean step {status.mean_step_us:6d} µs · "
        f"wd {status.watchdog_period_ms} ms · msg {status.message_period_ms} ms"
        f" · {age_s:.0f} s ago"
    )


class ThreadRow(Vertical):
    """Watchdog-page block for one thread: LEDs, counters and the editable periods."""

    def __init__(self, owner: VehicleKey, status: ThreadStatus) -> None:
        # No DOM id: a row of the previously selected vehicle may still be on its way out.
        super().__init__(classes="thread-row")
        self.owner = owner
        self.thread_id = status.thread_id
        self._first = status

    def compose(self) -> ComposeResult:
        # Built with the first status already in place, so a new row never shows blanks.
        t, first = self.thread_id, self._first
        with Horizontal(classes="line"):
            yield Label(_thread_title(first), id=f"name-{t}", classes="thread-name")
            for name, flag in zip(_LED_NAMES, _LED_FLAGS, strict=True):
                yield Led(name, lit=first.has(flag), id=f"led-{t}-{name}")
            yield Label(_thread_stats(first, 0.0), id=f"stats-{t}", classes="stats")
        with Horizontal(classes="line"):
            yield Label("watchdog ms", classes="field-label")
            yield Input(
                placeholder=str(first.watchdog_period_ms),
                id=f"wd-{t}",
                classes="param",
                compact=True,
            )
            yield Label("message ms", classes="field-label")
            yield Input(
                placeholder=str(first.message_period_ms),
                id=f"msg-{t}",
                classes="param",
                compact=True,
            )
            yield Button("Apply", id=f"apply-{t}", compact=True)
            yield Button("Restart", id=f"restart-{t}", compact=True)
            yield Label("", id=f"ack-{t}", classes="ack")

    def show(self, status: ThreadStatus, age_s: float) -> None:
        t = self.thread_id
        set_text(self.query_one(f"#name-{t}", Label), _thread_title(status))
        for name, flag in zip(_LED_NAMES, _LED_FLAGS, strict=True):
            self.query_one(f"#led-{t}-{name}", Led).set(status.has(flag))
        set_text(self.query_one(f"#stats-{t}", Label), _thread_stats(status, age_s))
        self.query_one(f"#wd-{t}", Input).placeholder = str(status.watchdog_period_ms)
        self.query_one(f"#msg-{t}", Input).placeholder = str(status.message_period_ms)


class DataPage(VerticalScroll):
    """A thread page listing one message type's fields, with sparklines where they help."""

    def __init__(self, key: str, cls: type[Any], rows: tuple[_Row, ...]) -> None:
        super().__init__(id=f"page-{key}", classes="data-page")
        self.key = key
        self.cls = cls
        self.rows = rows

    def compose(self) -> ComposeResult:
        yield Label("no data yet", id=f"{self.key}-age", classes="age")
        for row in self.rows:
            with Horizontal(classes="data-row"):
                yield Label(row.label, classes="data-label")
                yield Label("-", id=f"{self.key}-{row.attr}", classes="data-value")
                yield Label(row.unit, classes="data-unit")
                if row.spark:
                    yield Sparkline([], id=f"{self.key}-{row.attr}-spark", classes="spark")

    def show(self, state: VehicleState | None, now_s: float) -> None:
        msg = state.latest(self.cls) if state else None
        age = self.query_one(f"#{self.key}-age", Label)
        if state is None or msg is None:
            set_text(age, "no data yet")
            return
        last_s = state.history(self.cls)[-1][0]
        set_text(age, f"updated {now_s - last_s:.1f} s ago")
        for row in self.rows:
            value = getattr(msg, row.attr)
            set_text(self.query_one(f"#{self.key}-{row.attr}", Label), row.fmt(value))
            if row.spark:
                data = [v * row.scale for v in state.series(self.cls, row.attr)]
                self.query_one(f"#{self.key}-{row.attr}-spark", Sparkline).data = [
                    v for v in data if math.isfinite(v)
                ]


class ServoPage(VerticalScroll):
    """Pilot versus computer commands as bars, as the thesis's slider page did, and batteries."""

    def compose(self) -> ComposeResult:
        yield Label("no data yet", id="servo-age", classes="age")
        yield Label("", id="servo-mode")
        with Horizontal(classes="data-row"):
            yield Label("channel", classes="servo-ch")
            yield Label("pilot", classes="servo-head")
            yield Label("computer", classes="servo-head")
        for ch in range(1, 9):
            with Horizontal(classes="data-row"):
                yield Label(f"ch {ch}", classes="servo-ch")
                for who in ("pilot", "computer"):
                    yield ProgressBar(
                        total=_SERVO_SPAN_US,
                        show_eta=False,
                        show_percentage=False,
                        id=f"servo-{who}-{ch}",
                        classes="servo-bar",
                    )
                    yield Label("-", id=f"servo-{who}-{ch}-us", classes="servo-us")
        for which in ("avionics", "servo"):
            with Horizontal(classes="data-row"):
                yield Label(f"{which} battery", classes="data-label")
                yield ProgressBar(
                    total=255,
                    show_eta=False,
                    show_percentage=False,
                    id=f"battery-{which}",
                    classes="battery-bar",
                )
                yield Label("-", id=f"battery-{which}-raw", classes="data-value")

    def show(self, state: VehicleState | None, now_s: float) -> None:
        msg = state.latest(Servo) if state else None
        if state is None or msg is None:
            set_text(self.query_one("#servo-age", Label), "no data yet")
            return
        last_s = state.history(Servo)[-1][0]
        set_text(self.query_one("#servo-age", Label), f"updated {now_s - last_s:.1f} s ago")
        mode = "AUTOMATIC" if msg.flags & ServoFlag.AUTOMATIC else "manual"
        failsafe = "   FAILSAFE" if msg.flags & ServoFlag.FAILSAFE else ""
        set_text(self.query_one("#servo-mode", Label), f"mode {mode}{failsafe}")
        for who, values in (("pilot", msg.pilot_us), ("computer", msg.computer_us)):
            for ch, us in enumerate(values, start=1):
                bar = self.query_one(f"#servo-{who}-{ch}", ProgressBar)
                bar.update(progress=min(max(us - _SERVO_MIN_US, 0), _SERVO_SPAN_US))
                set_text(self.query_one(f"#servo-{who}-{ch}-us", Label), f"{us:5d} µs")
        for which, raw in (
            ("avionics", msg.avionics_battery_raw),
            ("servo", msg.servo_battery_raw),
        ):
            self.query_one(f"#battery-{which}", ProgressBar).update(progress=raw)
            set_text(
                self.query_one(f"#battery-{which}-raw", Label),
                f"raw {raw:3d} ({raw * 100 // 255}%)",
            )
