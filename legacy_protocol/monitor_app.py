"""Textual ground monitor for the legacy UDP protocol.

The thesis's ground station was a tabbed property sheet: one page per managed thread and a
watchdog page where thread and manager parameters could be changed.  This app keeps that shape in
a terminal: the watchdog page shows each thread's four status LEDs and editable periods, the data
pages show the latest values with sparklines of a short history, and a banner says plainly when
the link has gone quiet.  All networking lives in :mod:`legacy_protocol.monitor_link`; the app
drains it from a timer, so the state it reads is never touched by another thread.

Size: one Textual application (its pages, widgets and their styles); the protocol work lives
in monitor_link.py.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual.css.query import NoMatches
from textual.screen import ModalScreen, Screen
from textual.widgets import (
    Button,
    Footer,
    Header,
    Input,
    Label,
    ProgressBar,
    Select,
    Sparkline,
    Static,
    TabbedContent,
    TabPane,
)

from legacy_protocol.messages import (
    UNCHANGED,
    Command,
    Control,
    Estimator,
    Gps,
    GpsFix,
    Imu,
    RestartThread,
    Servo,
    ServoFlag,
    SetManagerParams,
    SetThreadParams,
    Stop,
    StopReason,
    ThreadFlag,
    ThreadId,
    ThreadStatus,
)
from legacy_protocol.monitor_link import (
    CommandOutcome,
    CommandSender,
    LinkError,
    MonitorLink,
    VehicleKey,
    VehicleState,
)

__all__ = ["DEFAULT_REFRESH_S", "DEFAULT_STALE_AFTER_S", "ConfirmScreen", "Led", "MonitorApp"]

log = logging.getLogger(__name__)

DEFAULT_STALE_AFTER_S = 3.0
"""Silence after which the link is shown as lost (three default status periods)."""

DEFAULT_REFRESH_S = 0.2
"""How often the sockets are drained and the visible page redrawn."""

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


_IMU_ROWS = (
    _Row("roll rate p", "p_rad_s", "deg/s", _num("+8.2f", _DEG_PER_RAD), _DEG_PER_RAD, True),
    _Row("pitch rate q", "q_rad_s", "deg/s", _num("+8.2f", _DEG_PER_RAD), _DEG_PER_RAD, True),
    _Row("yaw rate r", "r_rad_s", "deg/s", _num("+8.2f", _DEG_PER_RAD), _DEG_PER_RAD, True),
    _Row("accel x", "ax_m_s2", "m/s²", _num("+8.3f"), spark=True),
    _Row("accel y", "ay_m_s2", "m/s²", _num("+8.3f"), spark=True),
    _Row("accel z", "az_m_s2", "m/s²", _num("+8.3f"), spark=True),
    _Row("temperature", "temperature_c", "°C", _num("8.1f"), spark=True),
    _Row("frame count", "frame_count", "", _num("8d")),
)
_GPS_ROWS = (
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
_ESTIMATOR_ROWS = (
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
_CONTROL_ROWS = (
    _Row("aileron", "aileron", "", _num("+6.3f"), spark=True),
    _Row("elevator", "elevator", "", _num("+6.3f"), spark=True),
    _Row("rudder", "rudder", "", _num("+6.3f"), spark=True),
    _Row("throttle", "throttle", "", _num("6.3f"), spark=True),
    _Row("enabled", "enabled", "", lambda v: "yes" if v else "no"),
)


def _set_text(widget: Static, text: str) -> None:
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


def _parse_param(text: str, what: str, *, allow_zero: bool = False) -> int:
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
        _set_text(self.query_one(f"#name-{t}", Label), _thread_title(status))
        for name, flag in zip(_LED_NAMES, _LED_FLAGS, strict=True):
            self.query_one(f"#led-{t}-{name}", Led).set(status.has(flag))
        _set_text(self.query_one(f"#stats-{t}", Label), _thread_stats(status, age_s))
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
            _set_text(age, "no data yet")
            return
        last_s = state.history(self.cls)[-1][0]
        _set_text(age, f"updated {now_s - last_s:.1f} s ago")
        for row in self.rows:
            value = getattr(msg, row.attr)
            _set_text(self.query_one(f"#{self.key}-{row.attr}", Label), row.fmt(value))
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
            _set_text(self.query_one("#servo-age", Label), "no data yet")
            return
        last_s = state.history(Servo)[-1][0]
        _set_text(self.query_one("#servo-age", Label), f"updated {now_s - last_s:.1f} s ago")
        mode = "AUTOMATIC" if msg.flags & ServoFlag.AUTOMATIC else "manual"
        failsafe = "   FAILSAFE" if msg.flags & ServoFlag.FAILSAFE else ""
        _set_text(self.query_one("#servo-mode", Label), f"mode {mode}{failsafe}")
        for who, values in (("pilot", msg.pilot_us), ("computer", msg.computer_us)):
            for ch, us in enumerate(values, start=1):
                bar = self.query_one(f"#servo-{who}-{ch}", ProgressBar)
                bar.update(progress=min(max(us - _SERVO_MIN_US, 0), _SERVO_SPAN_US))
                _set_text(self.query_one(f"#servo-{who}-{ch}-us", Label), f"{us:5d} µs")
        for which, raw in (
            ("avionics", msg.avionics_battery_raw),
            ("servo", msg.servo_battery_raw),
        ):
            self.query_one(f"#battery-{which}", ProgressBar).update(progress=raw)
            _set_text(
                self.query_one(f"#battery-{which}-raw", Label),
                f"raw {raw:3d} ({raw * 100 // 255}%)",
            )


class MonitorApp(App[int]):
    """Terminal ground station for one or more aircraft speaking the legacy protocol."""

    TITLE = "UAV monitor"
    CSS = """
    #topbar { height: auto; padding: 0 1; }
    #link-status { width: 1fr; }
    #link-status.stale { background: $error; color: $text; text-style: bold; }
    #vehicle { width: 44; }
    #vehicle.single { display: none; }
    .thread-row { height: auto; border-bottom: solid $primary-darken-2; padding: 0 1; }
    .line { height: 1; }
    .thread-name { width: 16; text-style: bold; }
    .led { width: 9; }
    .led.on { color: $success; text-style: bold; }
    .led.off { color: $text-muted; }
    .stats { width: 1fr; }
    .field-label { width: 12; }
    .param { width: 12; margin-right: 2; }
    Button { margin-right: 1; }
    .ack { width: 1fr; }
    .ack.bad { color: $error; }
    .ack.good { color: $success; }
    #manager { height: auto; border-bottom: solid $secondary; padding: 0 1; }
    #stop { margin-left: 2; }
    #ack-stop { padding: 0 1; height: 1; }
    #thread-rows { height: auto; }
    .data-row { height: 1; }
    .data-label { width: 16; }
    .data-value { width: 16; text-align: right; margin-right: 1; }
    .data-unit { width: 7; }
    .spark { width: 40; height: 1; }
    .age { color: $text-muted; }
    .servo-ch { width: 8; }
    .servo-head { width: 38; }
    .servo-bar { width: 28; }
    .servo-us { width: 10; }
    .battery-bar { width: 30; }
    ConfirmScreen { align: center middle; }
    #dialog { width: 64; height: auto; border: thick $error; padding: 1 2; background: $surface; }
    #dialog-buttons { height: auto; margin-top: 1; }
    """
    BINDINGS: ClassVar = [Binding("q", "quit", "Quit")]

    def __init__(
        self,
        link: MonitorLink,
        sender: CommandSender,
        *,
        stale_after_s: float = DEFAULT_STALE_AFTER_S,
        refresh_s: float = DEFAULT_REFRESH_S,
    ) -> None:
        super().__init__()
        self.link = link
        self.sender = sender
        self.stale_after_s = stale_after_s
        self.refresh_s = refresh_s
        self.selected: VehicleKey | None = None
        self._vehicle_keys: list[VehicleKey] = []
        self._ack_targets: dict[int, str] = {}
        self._pages: list[DataPage] = []

    # -- layout --------------------------------------------------------------------------------

    def compose(self) -> ComposeResult:
        yield Header()
        with Horizontal(id="topbar"):
            yield Label("", id="link-status")
            yield Select[str]([], prompt="vehicle", id="vehicle", classes="single", compact=True)
            # STOP lives here, not on a tab, so it is one click away whatever page is shown.
            yield Button("STOP", variant="error", id="stop", compact=True)
        yield Label("", id="ack-stop", classes="ack")
        with TabbedContent(id="tabs"):
            with TabPane("Watchdog", id="tab-watchdog"), VerticalScroll():
                yield Vertical(id="thread-rows")
                with Vertical(id="manager"):
                    yield Label("manager: no status yet", id="manager-status")
                    with Horizontal(classes="line"):
                        yield Label("exec s", classes="field-label")
                        yield Input(placeholder="-", id="mgr-exec", classes="param", compact=True)
                        yield Label("status ms", classes="field-label")
                        yield Input(placeholder="-", id="mgr-status", classes="param", compact=True)
                        yield Label("granul. ms", classes="field-label")
                        yield Input(placeholder="-", id="mgr-gran", classes="param", compact=True)
                        yield Button("Apply", id="apply-manager", compact=True)
                        yield Label("", id="ack-manager", classes="ack")
            for title, key, cls, rows in (
                ("IMU", "imu", Imu, _IMU_ROWS),
                ("GPS", "gps", Gps, _GPS_ROWS),
            ):
                with TabPane(title, id=f"tab-{key}"):
                    yield DataPage(key, cls, rows)
            with TabPane("Servo", id="tab-servo"):
                yield ServoPage(id="page-servo")
            with TabPane("Estimator", id="tab-estimator"):
                yield DataPage("estimator", Estimator, _ESTIMATOR_ROWS)
            with TabPane("Control", id="tab-control"):
                yield DataPage("control", Control, _CONTROL_ROWS)
        yield Footer()

    def on_mount(self) -> None:
        host, port = self.link.address
        self.sub_title = (
            f"listening {host}:{port} · commands to {self.sender.target[0]}:{self.sender.target[1]}"
        )
        self._pages = list(self._home.query(DataPage))
        self.set_interval(self.refresh_s, self.tick)
        self.tick()

    # -- periodic work -------------------------------------------------------------------------

    @property
    def _home(self) -> Screen[Any]:
        """The main screen: timers keep firing under a dialog, whose DOM lacks our widgets."""
        return self.screen_stack[0]

    @property
    def vehicle(self) -> VehicleState | None:
        """The aircraft the pages show and commands go to."""
        if self.selected is None:
            return None
        return self.link.fleet.vehicles.get(self.selected)

    def tick(self) -> None:
        """Drain both sockets, settle commands, redraw what is visible."""
        self.link.poll()
        outcomes = self.sender.poll()
        try:
            self._redraw(outcomes)
        except (NoMatches, IndexError):
            # Only while the app shuts down: a last timer tick after the widgets are gone.
            log.debug("tick after widgets were removed")

    def _redraw(self, outcomes: list[CommandOutcome]) -> None:
        for outcome in outcomes:
            self._show_outcome(outcome)
        self._sync_vehicles()
        now = self.link.now()
        state = self.vehicle
        self._show_link(state, now)
        active = self._home.query_one("#tabs", TabbedContent).active
        if active == "tab-watchdog":
            self._show_watchdog(state, now)
        elif active == "tab-servo":
            self._home.query_one("#page-servo", ServoPage).show(state, now)
        else:
            for page in self._pages:
                if active == f"tab-{page.key}":
                    page.show(state, now)

    def _sync_vehicles(self) -> None:
        keys = sorted(self.link.fleet.vehicles)
        if keys == self._vehicle_keys:
            return
        self._vehicle_keys = keys
        select = self._home.query_one("#vehicle", Select)
        select.set_options((f"vehicle {k[0]} @ {k[1]}:{k[2]}", self._key_text(k)) for k in keys)
        select.set_class(len(keys) <= 1, "single")
        if self.selected is None and keys:
            self._select(keys[0])
        elif self.selected is not None:
            select.value = self._key_text(self.selected)

    @staticmethod
    def _key_text(key: VehicleKey) -> str:
        return f"{key[0]}|{key[1]}|{key[2]}"

    def _select(self, key: VehicleKey) -> None:
        if key != self.selected:
            self.selected = key  # the watchdog page drops the old vehicle's rows on redraw
            for label in self._home.query(".ack").results(Label):
                label.update("")
        select = self._home.query_one("#vehicle", Select)
        if select.value != self._key_text(key):
            select.value = self._key_text(key)

    def on_select_changed(self, event: Select.Changed) -> None:
        if event.select.id != "vehicle" or not isinstance(event.value, str):
            return
        vid, host, port = event.value.split("|")
        key: VehicleKey = (int(vid), host, int(port))
        if key in self.link.fleet.vehicles:
            self._select(key)
            self.tick()

    def on_tabbed_content_tab_activated(self, event: TabbedContent.TabActivated) -> None:
        self.tick()

    def _show_link(self, state: VehicleState | None, now_s: float) -> None:
        status = self._home.query_one("#link-status", Label)
        fleet = self.link.fleet
        bad = f" · {fleet.malformed} malformed" if fleet.malformed else ""
        if state is None:
            host, port = self.link.address
            text = f"waiting for data on UDP {host}:{port}{bad}"
            stale = False
        else:
            silence = state.silence_s(now_s)
            who = f"vehicle {state.vehicle_id} @ {state.source[0]}:{state.source[1]}"
            stale = silence >= self.stale_after_s
            if stale:
                text = f"NO DATA FOR {silence:.0f} s from {who} (waiting, will resume){bad}"
            else:
                text = (
                    f"{who} · heard {silence:.1f} s ago · {state.datagrams} datagrams"
                    f" · {state.lost} lost{bad}"
                )
        _set_text(status, text)
        status.set_class(stale, "stale")

    def _show_watchdog(self, state: VehicleState | None, now_s: float) -> None:
        if state is None:
            return
        rows = self._home.query_one("#thread-rows", Vertical)
        existing: dict[int, ThreadRow] = {}
        for old in rows.query(ThreadRow):
            if old.owner == state.key:
                existing[old.thread_id] = old
            elif old.is_attached:
                old.remove()
        for tid in sorted(state.threads):
            row = existing.get(tid)
            if row is None:
                row = ThreadRow(state.key, state.threads[tid])
                later = [r for t, r in existing.items() if t > tid]
                rows.mount(row, before=min(later, key=lambda r: r.thread_id) if later else None)
                existing[tid] = row
                continue
            if row.is_mounted and row.children:
                row.show(state.threads[tid], now_s - state.thread_heard_s[tid])
        mgr = state.manager
        if mgr is not None:
            exec_text = "unlimited" if mgr.execution_time_s == 0 else f"{mgr.execution_time_s} s"
            _set_text(
                self._home.query_one("#manager-status", Label),
                f"manager: elapsed {mgr.elapsed_ms / 1000:.1f} s · execution time {exec_text}"
                f" · status period {mgr.status_period_ms} ms · granularity"
                f" {mgr.granularity_ms} ms · {mgr.thread_count} threads",
            )
            self._home.query_one("#mgr-exec", Input).placeholder = str(mgr.execution_time_s)
            self._home.query_one("#mgr-status", Input).placeholder = str(mgr.status_period_ms)
            self._home.query_one("#mgr-gran", Input).placeholder = str(mgr.granularity_ms)

    # -- commands ------------------------------------------------------------------------------

    def _ack_label(self, target: str) -> Label | None:
        found = self._home.query(f"#ack-{target}")
        return found.first(Label) if found else None

    def _say(self, target: str, text: str, *, good: bool | None = None) -> None:
        label = self._ack_label(target)
        if label is None:
            return
        label.update(text)
        label.set_class(good is True, "good")
        label.set_class(good is False, "bad")

    def _send(self, target: str, command: Command) -> None:
        state = self.vehicle
        if state is None:
            self._say(target, "no vehicle heard yet: nothing to command", good=False)
            return
        try:
            seq = self.sender.send(command, vehicle_id=state.vehicle_id)
        except (LinkError, ValueError) as exc:
            self._say(target, str(exc), good=False)
            return
        self._ack_targets[seq] = target
        self._say(target, f"sent #{seq}, waiting for ACK…")

    def _show_outcome(self, outcome: CommandOutcome) -> None:
        target = self._ack_targets.pop(outcome.seq, None)
        if target is None:
            return
        self._say(target, outcome.text, good=outcome.accepted)
        if not outcome.accepted:
            return
        # Clear what was applied so the placeholders show the aircraft's values again.
        if isinstance(outcome.command, SetManagerParams):
            ids = ["mgr-exec", "mgr-status", "mgr-gran"]
        elif isinstance(outcome.command, SetThreadParams):
            ids = [f"wd-{outcome.command.thread_id}", f"msg-{outcome.command.thread_id}"]
        else:
            ids = []
        for iid in ids:
            found = self._home.query(f"#{iid}")
            if found:
                found.first(Input).value = ""

    def _apply_thread(self, tid: int) -> None:
        try:
            wd = _parse_param(self._home.query_one(f"#wd-{tid}", Input).value, "watchdog period ms")
            msg = _parse_param(
                self._home.query_one(f"#msg-{tid}", Input).value, "message period ms"
            )
        except ValueError as exc:
            self._say(str(tid), str(exc), good=False)
            return
        if wd == UNCHANGED and msg == UNCHANGED:
            self._say(str(tid), "type a new period first", good=False)
            return
        self._send(str(tid), SetThreadParams(tid, wd, msg))

    def _apply_manager(self) -> None:
        try:
            exec_s = _parse_param(
                self._home.query_one("#mgr-exec", Input).value, "execution time s", allow_zero=True
            )
            status_ms = _parse_param(
                self._home.query_one("#mgr-status", Input).value, "status period ms"
            )
            gran_ms = _parse_param(self._home.query_one("#mgr-gran", Input).value, "granularity ms")
        except ValueError as exc:
            self._say("manager", str(exc), good=False)
            return
        if exec_s == status_ms == gran_ms == UNCHANGED:
            self._say("manager", "type a new value first", good=False)
            return
        self._send("manager", SetManagerParams(exec_s, status_ms, gran_ms))

    def _confirm_stop(self) -> None:
        state = self.vehicle
        if state is None:
            self._say("stop", "no vehicle heard yet: nothing to stop", good=False)
            return
        vid = state.vehicle_id

        def done(confirmed: bool | None) -> None:
            if confirmed:
                self._send("stop", Stop(StopReason.OPERATOR))
            else:
                self._say("stop", "STOP cancelled")

        self.push_screen(
            ConfirmScreen(
                f"Stop vehicle {vid}? Every on-board thread stops, logs are closed and the"
                " application exits. It cannot be restarted from here.",
                "STOP",
            ),
            done,
        )

    def _confirm_restart(self, tid: int) -> None:
        def done(confirmed: bool | None) -> None:
            if confirmed:
                self._send(str(tid), RestartThread(tid))

        try:
            name = ThreadId(tid).name
        except ValueError:
            name = f"thread {tid}"
        self.push_screen(ConfirmScreen(f"Restart thread {tid} ({name})?", "Restart"), done)

    def on_button_pressed(self, event: Button.Pressed) -> None:
        bid = event.button.id or ""
        if bid == "stop":
            self._confirm_stop()
        elif bid == "apply-manager":
            self._apply_manager()
        elif bid.startswith("apply-"):
            self._apply_thread(int(bid.removeprefix("apply-")))
        elif bid.startswith("restart-"):
            self._confirm_restart(int(bid.removeprefix("restart-")))

    def on_input_submitted(self, event: Input.Submitted) -> None:
        iid = event.input.id or ""
        if iid.startswith("mgr-"):
            self._apply_manager()
        elif iid.startswith(("wd-", "msg-")):
            self._apply_thread(int(iid.split("-", 1)[1]))
