"""Textual ground monitor for the legacy UDP protocol.

The thesis's ground station was a tabbed property sheet: one page per managed thread and a
watchdog page where thread and manager parameters could be changed.  This app keeps that shape in
a terminal: the watchdog page shows each thread's four status LEDs and editable periods, the data
pages show the latest values with sparklines of a short history, and a banner says plainly when
the link has gone quiet.  All networking lives in :mod:`legacy_protocol.monitor_link`; the app
drains it from a timer, so the state it reads is never touched by another thread.  The widgets
it lays out are in :mod:`legacy_protocol.monitor_widgets`; this module is the application: the
layout and styles, the redraw, and the commands the operator sends.
"""

from __future__ import annotations

import logging
from typing import Any, ClassVar

from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual.css.query import NoMatches
from textual.screen import Screen
from textual.widgets import (
    Button,
    Footer,
    Header,
    Input,
    Label,
    Select,
    TabbedContent,
    TabPane,
)

from legacy_protocol.messages import (
    UNCHANGED,
    Command,
    Control,
    Estimator,
    Gps,
    Imu,
    RestartThread,
    SetManagerParams,
    SetThreadParams,
    Stop,
    StopReason,
    ThreadId,
)
from legacy_protocol.monitor_link import (
    CommandOutcome,
    CommandSender,
    LinkError,
    MonitorLink,
    VehicleKey,
    VehicleState,
)
from legacy_protocol.monitor_widgets import (
    CONTROL_ROWS,
    ESTIMATOR_ROWS,
    GPS_ROWS,
    IMU_ROWS,
    ConfirmScreen,
    DataPage,
    ServoPage,
    ThreadRow,
    parse_param,
    set_text,
)

__all__ = ["DEFAULT_REFRESH_S", "DEFAULT_STALE_AFTER_S", "MonitorApp"]

log = logging.getLogger(__name__)

DEFAULT_STALE_AFTER_S = 3.0
"""Silence after which the link is shown as lost (three default status periods)."""

DEFAULT_REFRESH_S = 0.2
"""How often the sockets are drained and the visible page redrawn."""
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
                ("IMU", "imu", Imu, IMU_ROWS),
                ("GPS", "gps", Gps, GPS_ROWS),
            ):
                with TabPane(title, id=f"tab-{key}"):
                    yield DataPage(key, cls, rows)
            with TabPane("Servo", id="tab-servo"):
                yield ServoPage(id="page-servo")
            with TabPane("Estimator", id="tab-estimator"):
                yield DataPage("estimator", Estimator, ESTIMATOR_ROWS)
            with TabPane("Control", id="tab-control"):
                yield DataPage("control", Control, CONTROL_ROWS)
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
        set_text(status, text)
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
            set_text(
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
            wd = parse_param(self._home.query_one(f"#wd-{tid}", Input).value, "watchdog period ms")
            msg = parse_param(
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
            exec_s = parse_param(
                self._home.query_one("#mgr-exec", Input).value, "execution time s", allow_zero=True
            )
            status_ms = parse_param(
                self._home.query_one("#mgr-status", Input).value, "status period ms"
            )
            gran_ms = parse_param(self._home.query_one("#mgr-gran", Input).value, "granularity ms")
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
