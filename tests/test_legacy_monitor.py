"""Ground monitor: link and command sender against a fake aircraft on real UDP sockets, the TUI
driven headless through Textual's pilot, and the ``--json`` command line."""

from __future__ import annotations

import asyncio
import json
import os
import queue
import select
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from textual.pilot import Pilot
from textual.widgets import Input, Label, Select, Sparkline, Static

from legacy_protocol import cli
from legacy_protocol.codec import Decoded, decode, encode
from legacy_protocol.messages import (
    UNCHANGED,
    AckResult,
    CommandAck,
    Estimator,
    Gps,
    Imu,
    ManagerStatus,
    Payload,
    RestartThread,
    Servo,
    SetManagerParams,
    SetThreadParams,
    Stop,
    ThreadStatus,
)
from legacy_protocol.monitor_app import MonitorApp
from legacy_protocol.monitor_link import CommandSender, LinkError, MonitorLink
from legacy_protocol.monitor_widgets import ConfirmScreen, Led

REPO = Path(__file__).resolve().parents[1]
WAIT_S = 5.0


@pytest.fixture(autouse=True)
def no_leaked_threads() -> Iterator[None]:
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 2.0
    while (extra := set(threading.enumerate()) - before) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not extra, f"threads left running: {extra}"


class FakeAircraft:
    """Plays the aircraft on a real UDP socket: sends messages, answers commands with ACKs.

    ``result_for`` picks the ACK result per command; ``answer=False`` makes it stay silent so the
    monitor's timeout can be seen.
    """

    def __init__(
        self,
        monitor: tuple[str, int],
        *,
        vehicle_id: int = 7,
        answer: bool = True,
        result_for: Callable[[Payload], int] = lambda _cmd: AckResult.ACCEPTED,
        bogus_ack_first: bool = False,
    ) -> None:
        self.monitor = monitor
        self.vehicle_id = vehicle_id
        self.answer = answer
        self.result_for = result_for
        self.bogus_ack_first = bogus_ack_first
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.seq = 0
        self.commands: queue.Queue[tuple[Decoded, tuple[str, int]]] = queue.Queue()
        self.seen: list[Decoded] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="fake-aircraft", daemon=True)
        self._thread.start()

    @property
    def command_addr(self) -> tuple[str, int]:
        host, port = self.sock.getsockname()
        return host, port

    def send(
        self, msg: Payload, *, seq: int | None = None, to: tuple[str, int] | None = None
    ) -> None:
        self.seq = self.seq + 1 if seq is None else seq
        datagram = encode(msg, vehicle_id=self.vehicle_id, seq=self.seq, t_ns=time.time_ns())
        self.sock.sendto(datagram, to or self.monitor)

    def send_raw(self, data: bytes) -> None:
        self.sock.sendto(data, self.monitor)

    def _serve(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.sock], [], [], 0.05)
            if not ready:
                continue
            try:
                data, source = self.sock.recvfrom(65536)
            except OSError:
                return
            result = decode(data)
            if not isinstance(result, Decoded) or result.header.type_code < 0x80:
                continue
            self.seen.append(result)
            self.commands.put((result, source))
            if not self.answer:
                continue
            if self.bogus_ack_first:
                wrong = CommandAck(result.header.type_code, 0, (result.header.seq + 99) % 2**32)
                self.send(wrong, to=source)
            ack = CommandAck(
                result.header.type_code, int(self.result_for(result.payload)), result.header.seq
            )
            self.send(ack, to=source)

    def next_command(self, timeout_s: float = WAIT_S) -> Decoded:
        return self.commands.get(timeout=timeout_s)[0]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.sock.close()


@pytest.fixture
def link() -> Iterator[MonitorLink]:
    with MonitorLink(0, host="127.0.0.1") as lk:
        yield lk


@pytest.fixture
def aircraft(link: MonitorLink) -> Iterator[FakeAircraft]:
    fake = FakeAircraft(link.address)
    yield fake
    fake.close()


def pump_until(link: MonitorLink, cond: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        link.wait(0.05)
        link.poll()


def status(tid: int, flags: int, name: str, **kw: int) -> ThreadStatus:
    values = {
        "restarts": 0,
        "mean_step_us": 850,
        "watchdog_period_ms": 500,
        "message_period_ms": 1000,
    }
    values.update(kw)
    return ThreadStatus(tid, flags, name=name, **values)


# Values exact in float32, so what comes back compares equal to what was sent.
IMU = Imu(0.125, -0.25, 0.5, 0.0625, -0.5, -9.75, 35.5, 123456)
GPS = Gps(40.1106, -88.2073, 221.5, 12.5, -3.25, 0.5, 1.75, 0.875, 1.5, 1.125, 35.0, 2.5, 2, 9)
SERVO = Servo(
    (1500, 1480, 1100, 1520, 1900, 1500, 1500, 1500),
    (1510, 1490, 1200, 1500, 0, 0, 0, 0),
    98,
    87,
    1,
)
MANAGER = ManagerStatus(61234, 600, 1000, 50, 5)


# ---------------------------------------------------------------------------------------------
# Link and state model


def test_link_builds_per_vehicle_state(link: MonitorLink, aircraft: FakeAircraft) -> None:
    aircraft.send(status(1, 0b1111, "imu", restarts=2))
    aircraft.send(status(4, 0b0011, "estimator"))
    aircraft.send(MANAGER)
    for i in range(3):
        aircraft.send(Imu(0.25 * i, 0, 0, 0, 0, -9.75, 30.0 + i, i))
    aircraft.send(GPS, seq=aircraft.seq + 4)  # three datagrams "lost" before this one
    aircraft.send_raw(b"\x10\x07\x30\x00" + b"\0" * 10)  # short IMU
    aircraft.send_raw(b"\x42" + b"\0" * 47)  # unknown type
    aircraft.send(Stop())  # a command reaching the monitor port is not the monitor's business
    pump_until(link, lambda: link.fleet.received == 10, "ten datagrams")

    fleet = link.fleet
    assert fleet.malformed == 2 and fleet.unexpected_commands == 1
    assert set(fleet.malformed_reasons) == {"short datagram", "unknown type 0x42"}
    assert fleet.last_error is not None and fleet.last_error[0] == aircraft.command_addr
    [state] = fleet.ordered()
    assert state.key == (7, *aircraft.command_addr)
    assert state.threads[1].restarts == 2 and state.threads[4].name == "estimator"
    assert state.manager == MANAGER
    assert state.latest(Imu) == Imu(0.5, 0, 0, 0, 0, -9.75, 32.0, 2)
    assert state.series(Imu, "temperature_c") == [30.0, 31.0, 32.0]
    assert state.latest(Gps) == GPS and state.latest(Servo) is None
    assert state.lost == 3
    assert state.datagrams == 7 and state.by_type["IMU"] == 3
    assert state.malformed == 2 and fleet.malformed_by_source[aircraft.command_addr] == 2
    assert 0 <= state.silence_s(link.now()) < WAIT_S


def test_history_is_bounded(aircraft: FakeAircraft) -> None:
    with MonitorLink(0, host="127.0.0.1", history_len=5) as small:
        small_fake = FakeAircraft(small.address)
        try:
            for i in range(12):
                small_fake.send(Imu(0, 0, 0, 0, 0, 0, float(i), i))
            pump_until(small, lambda: small.fleet.received == 12, "twelve IMU messages")
        finally:
            small_fake.close()
        [state] = small.fleet.ordered()
        assert state.series(Imu, "temperature_c") == [7.0, 8.0, 9.0, 10.0, 11.0]


def test_two_aircraft_are_kept_apart(link: MonitorLink, aircraft: FakeAircraft) -> None:
    other = FakeAircraft(link.address, vehicle_id=3)
    try:
        aircraft.send(IMU)
        other.send(GPS)
        pump_until(link, lambda: len(link.fleet.vehicles) == 2, "two vehicles")
    finally:
        other.close()
    first, second = link.fleet.ordered()
    assert first.vehicle_id == 3 and first.latest(Gps) == GPS and first.latest(Imu) is None
    assert second.vehicle_id == 7 and second.latest(Imu) == IMU


def test_command_is_matched_with_its_ack(aircraft: FakeAircraft) -> None:
    with CommandSender(aircraft.command_addr, timeout_s=WAIT_S) as sender:
        outcome = sender.request(SetThreadParams(1, UNCHANGED, 250), vehicle_id=7)
        got = aircraft.next_command()
    assert got.payload == SetThreadParams(1, UNCHANGED, 250)
    assert got.header.vehicle_id == 7 and got.header.seq == outcome.seq
    assert outcome.accepted and outcome.ack is not None and outcome.ack.command_seq == outcome.seq
    assert "SET_THREAD_PARAMS" in outcome.text and "accepted" in outcome.text


def test_rejection_and_stray_acks(link: MonitorLink) -> None:
    fake = FakeAircraft(
        link.address, result_for=lambda _c: AckResult.BAD_VALUE, bogus_ack_first=True
    )
    try:
        with CommandSender(fake.command_addr, timeout_s=WAIT_S) as sender:
            first = sender.send(SetManagerParams(granularity_ms=0), vehicle_id=7)
            second = sender.send(Stop(), vehicle_id=7)
            settled: list[Any] = []
            deadline = time.monotonic() + WAIT_S
            while len(settled) < 2 and time.monotonic() < deadline:
                select.select([sender], [], [], 0.05)
                settled += sender.poll()
            assert [o.seq for o in settled] == [first, second]
            assert all(not o.accepted and "rejected: bad value" in o.text for o in settled)
            assert sender.unmatched_acks == 2 and sender.pending == 0
    finally:
        fake.close()


def test_command_times_out_without_ack(link: MonitorLink) -> None:
    silent = FakeAircraft(link.address, answer=False)
    try:
        with CommandSender(silent.command_addr, timeout_s=0.3) as sender:
            t0 = time.monotonic()
            outcome = sender.request(Stop(), vehicle_id=7)
            waited = time.monotonic() - t0
            assert silent.next_command().payload == Stop()
    finally:
        silent.close()
    assert outcome.ack is None and not outcome.accepted
    assert 0.3 <= waited < 2.0
    # the text says how long it waited: the 0.3 s timeout, or a little more on a busy machine
    assert 0.3 <= outcome.elapsed_s <= waited
    assert f"no ACK after {outcome.elapsed_s:.1f} s" in outcome.text


def test_two_monitors_share_the_port_for_broadcast() -> None:
    with MonitorLink(0) as first, MonitorLink(first.address[1]) as second:
        port = first.address[1]
        assert second.address[1] == port
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        tx.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        try:
            tx.sendto(encode(IMU, vehicle_id=9, seq=1, t_ns=0), ("127.255.255.255", port))
        except OSError as exc:
            pytest.skip(f"no loopback broadcast here: {exc}")
        finally:
            tx.close()
        for lk in (first, second):
            pump_until(lk, lambda lk=lk: lk.fleet.received == 1, "the broadcast")  # type: ignore[misc]
            assert lk.fleet.ordered()[0].latest(Imu) == IMU


def test_busy_port_is_a_clear_error() -> None:
    blocker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    blocker.bind(("127.0.0.1", 0))  # no SO_REUSEPORT: nobody may share it
    port = blocker.getsockname()[1]
    try:
        with pytest.raises(LinkError, match=f"cannot listen on UDP 127.0.0.1:{port}"):
            MonitorLink(port, host="127.0.0.1")
    finally:
        blocker.close()


# ---------------------------------------------------------------------------------------------
# TUI, headless


def screen_text(app: MonitorApp, selector: str) -> str:
    return str(app.screen_stack[0].query_one(selector, Static).content)


def laid_out(app: MonitorApp, selector: str, *, dialog: bool = False) -> bool:
    """The widget exists and has been given a place on screen, so a click can land on it."""
    screen = app.screen if dialog else app.screen_stack[0]
    found = screen.query(selector)
    return bool(found) and found.first().region.area > 0


async def until(pilot: Pilot[Any], cond: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await pilot.pause(0.05)


def run_app(
    link: MonitorLink,
    fake: FakeAircraft,
    scenario: Callable[[MonitorApp, Pilot[Any]], Any],
    **kw: Any,
) -> None:
    async def main() -> None:
        with CommandSender(fake.command_addr, timeout_s=WAIT_S) as sender:
            app = MonitorApp(link, sender, refresh_s=0.05, **kw)
            async with app.run_test(size=(150, 60)) as pilot:
                await scenario(app, pilot)

    asyncio.run(asyncio.wait_for(main(), timeout=30))


def test_tui_watchdog_page_shows_leds_and_sends_edited_period(
    link: MonitorLink, aircraft: FakeAircraft
) -> None:
    async def scenario(app: MonitorApp, pilot: Pilot[Any]) -> None:
        assert "waiting for data" in screen_text(app, "#link-status")
        aircraft.send(status(1, 0b1111, "imu", restarts=3, mean_step_us=850))
        aircraft.send(status(4, 0b0011, "estimator", restarts=4))
        aircraft.send(MANAGER)
        await until(pilot, lambda: laid_out(app, "#led-4-alive"), "thread 4 row")
        await until(pilot, lambda: laid_out(app, "#apply-1"), "thread 1 row")
        assert app.query_one("#led-4-run", Led).lit is True

        def led(tid: int, name: str) -> str:
            return screen_text(app, f"#led-{tid}-{name}")

        assert [led(1, n) for n in ("init", "run", "loop", "alive")] == [
            "● init",
            "● run",
            "● loop",
            "● alive",
        ]
        assert [led(4, n) for n in ("init", "run", "loop", "alive")] == [
            "● init",
            "● run",
            "○ loop",
            "○ alive",
        ]
        assert app.query_one("#led-4-alive").has_class("off")
        assert screen_text(app, "#name-4") == "4 estimator"
        stats = screen_text(app, "#stats-1")
        assert "restarts   3" in stats and "850 µs" in stats and "wd 500 ms" in stats
        manager = screen_text(app, "#manager-status")
        assert "execution time 600 s" in manager and "granularity 50 ms" in manager
        assert "vehicle 7" in screen_text(app, "#link-status")

        # A typo is caught before anything goes on the air.
        await pilot.click("#msg-1")
        await pilot.press(*"2x0")
        await pilot.click("#apply-1")
        assert "not a whole number" in screen_text(app, "#ack-1")
        assert aircraft.commands.empty()

        app.query_one("#msg-1", Input).value = ""
        await pilot.click("#msg-1")
        await pilot.press(*"250")
        await pilot.click("#apply-1")
        await until(pilot, lambda: not aircraft.commands.empty(), "the command")
        sent = aircraft.next_command(0)
        assert sent.payload == SetThreadParams(1, UNCHANGED, 250)
        await until(pilot, lambda: "accepted" in screen_text(app, "#ack-1"), "the ACK")
        assert f"#{sent.header.seq}" in screen_text(app, "#ack-1")
        assert app.query_one("#msg-1", Input).value == ""

    run_app(link, aircraft, scenario)


def test_tui_manager_params_and_rejection(link: MonitorLink) -> None:
    fake = FakeAircraft(link.address, result_for=lambda _c: AckResult.BAD_VALUE)

    async def scenario(app: MonitorApp, pilot: Pilot[Any]) -> None:
        fake.send(MANAGER)
        await until(pilot, lambda: "elapsed 61.2 s" in screen_text(app, "#manager-status"), "mgr")
        await until(pilot, lambda: laid_out(app, "#mgr-gran"), "manager inputs")
        await pilot.click("#mgr-gran")
        await pilot.press(*"2000", "enter")
        await until(pilot, lambda: not fake.commands.empty(), "the command")
        assert fake.next_command(0).payload == SetManagerParams(UNCHANGED, UNCHANGED, 2000)
        await until(pilot, lambda: "rejected" in screen_text(app, "#ack-manager"), "the ACK")
        assert "rejected: bad value" in screen_text(app, "#ack-manager")
        assert app.query_one("#ack-manager").has_class("bad")
        assert app.query_one("#mgr-gran", Input).value == "2000"  # kept for correction

    try:
        run_app(link, fake, scenario)
    finally:
        fake.close()


def test_tui_stop_needs_confirmation(link: MonitorLink, aircraft: FakeAircraft) -> None:
    async def scenario(app: MonitorApp, pilot: Pilot[Any]) -> None:
        aircraft.send(status(1, 0b1111, "imu"))
        await until(pilot, lambda: app.vehicle is not None, "a vehicle")
        await pilot.click("#stop")
        await until(pilot, lambda: isinstance(app.screen, ConfirmScreen), "the dialog")
        await until(pilot, lambda: laid_out(app, "#cancel", dialog=True), "dialog buttons")
        assert "Stop vehicle 7?" in str(app.screen.query_one("#question", Label).content)
        await pilot.click("#cancel")
        await until(pilot, lambda: not isinstance(app.screen, ConfirmScreen), "dialog closed")
        assert "cancelled" in screen_text(app, "#ack-stop")
        assert aircraft.commands.empty()

        await pilot.click("#stop")
        await until(pilot, lambda: isinstance(app.screen, ConfirmScreen), "the dialog")
        await until(pilot, lambda: laid_out(app, "#confirm", dialog=True), "dialog buttons")
        await pilot.click("#confirm")
        await until(pilot, lambda: not aircraft.commands.empty(), "STOP")
        got = aircraft.next_command(0)
        assert got.payload == Stop(0) and got.header.vehicle_id == 7
        await until(pilot, lambda: "STOP" in screen_text(app, "#ack-stop"), "the ACK")
        assert "accepted" in screen_text(app, "#ack-stop")

        # Restarting a thread is guarded the same way.
        await until(pilot, lambda: laid_out(app, "#restart-1"), "thread 1 row")
        await pilot.click("#restart-1")
        await until(pilot, lambda: isinstance(app.screen, ConfirmScreen), "the dialog")
        assert "Restart thread 1 (IMU)?" in str(app.screen.query_one("#question", Label).content)
        await until(pilot, lambda: laid_out(app, "#confirm", dialog=True), "dialog buttons")
        await pilot.click("#confirm")
        await until(pilot, lambda: not aircraft.commands.empty(), "RESTART_THREAD")
        assert aircraft.next_command(0).payload == RestartThread(1)
        await until(pilot, lambda: "RESTART_THREAD" in screen_text(app, "#ack-1"), "the ACK")

    run_app(link, aircraft, scenario)


def test_tui_shows_no_data_then_recovers(link: MonitorLink, aircraft: FakeAircraft) -> None:
    async def scenario(app: MonitorApp, pilot: Pilot[Any]) -> None:
        aircraft.send(status(1, 0b1111, "imu"))
        await until(pilot, lambda: "heard" in screen_text(app, "#link-status"), "first data")
        assert not app.query_one("#link-status").has_class("stale")
        await until(pilot, lambda: "NO DATA FOR" in screen_text(app, "#link-status"), "silence")
        assert app.query_one("#link-status").has_class("stale")
        assert "vehicle 7" in screen_text(app, "#link-status")
        aircraft.send(status(1, 0b0111, "imu"))
        await until(pilot, lambda: "heard" in screen_text(app, "#link-status"), "recovery")
        assert not app.query_one("#link-status").has_class("stale")
        await until(pilot, lambda: screen_text(app, "#led-1-alive") == "○ alive", "new status")

    run_app(link, aircraft, scenario, stale_after_s=0.4)


def test_tui_data_pages(link: MonitorLink, aircraft: FakeAircraft) -> None:
    est = Estimator(0.1, -0.05, 1.57, 120.0, -35.5, -80.0, 20.0, 1.0, -0.5, 0.001, -0.002, 0.0005)

    async def scenario(app: MonitorApp, pilot: Pilot[Any]) -> None:
        for i in range(4):
            aircraft.send(Imu(0.01, -0.02, 0.5, 0.1, -0.2, -9.8, 30.0 + i, i))
        aircraft.send(GPS)
        aircraft.send(SERVO)
        aircraft.send(est)
        await until(pilot, lambda: app.vehicle is not None and app.vehicle.datagrams == 7, "data")

        await pilot.click("#--content-tab-tab-imu")
        await until(pilot, lambda: screen_text(app, "#imu-frame_count").strip() == "3", "IMU")
        assert screen_text(app, "#imu-r_rad_s").strip() == "+28.65"  # 0.5 rad/s in deg/s
        assert screen_text(app, "#imu-temperature_c").strip() == "33.0"
        assert list(app.query_one("#imu-temperature_c-spark", Sparkline).data or []) == [
            30.0,
            31.0,
            32.0,
            33.0,
        ]

        await pilot.click("#--content-tab-tab-gps")
        await until(pilot, lambda: screen_text(app, "#gps-fix_type") == "DGPS", "GPS")
        assert screen_text(app, "#gps-lat_deg") == "+40.1106000"
        assert screen_text(app, "#gps-satellites") == "9"

        await pilot.click("#--content-tab-tab-servo")
        await until(pilot, lambda: screen_text(app, "#servo-pilot-3-us") == " 1100 µs", "servo")
        bars = app.screen_stack[0]
        assert bars.query_one("#servo-pilot-3").progress == 100  # type: ignore[attr-defined]
        assert bars.query_one("#servo-computer-3").progress == 200  # type: ignore[attr-defined]
        assert bars.query_one("#battery-avionics").progress == 98  # type: ignore[attr-defined]
        assert screen_text(app, "#battery-servo-raw") == "raw  87 (34%)"
        assert screen_text(app, "#servo-mode") == "mode AUTOMATIC"

        await pilot.click("#--content-tab-tab-estimator")
        await until(pilot, lambda: screen_text(app, "#estimator-roll_rad") != "-", "estimator")
        assert screen_text(app, "#estimator-roll_rad").strip() == "+5.73"
        assert screen_text(app, "#estimator-down_m").strip() == "-80.0"

        await pilot.click("#--content-tab-tab-control")
        await until(pilot, lambda: "no data yet" in screen_text(app, "#control-age"), "control")

    run_app(link, aircraft, scenario)


def test_tui_vehicle_selector(link: MonitorLink, aircraft: FakeAircraft) -> None:
    other = FakeAircraft(link.address, vehicle_id=3)

    async def scenario(app: MonitorApp, pilot: Pilot[Any]) -> None:
        aircraft.send(status(1, 0b1111, "imu"))
        await until(pilot, lambda: app.vehicle is not None, "first vehicle")
        selector = app.query_one("#vehicle", Select)
        assert selector.has_class("single")  # one aircraft: no selector to distract
        assert "vehicle 7" in screen_text(app, "#link-status")
        other.send(status(2, 0b0001, "gps-3"))
        await until(pilot, lambda: not selector.has_class("single"), "selector shown")
        assert "vehicle 7" in screen_text(app, "#link-status")  # selection is kept
        selector.value = f"3|{other.command_addr[0]}|{other.command_addr[1]}"
        await until(pilot, lambda: "vehicle 3" in screen_text(app, "#link-status"), "switch")
        await until(pilot, lambda: not app.query("#name-1"), "vehicle 7's rows gone")
        await until(pilot, lambda: bool(app.query("#name-2")), "vehicle 3's thread")
        assert screen_text(app, "#name-2") == "2 gps-3"  # filled in as soon as it appears
        assert screen_text(app, "#led-2-init") == "● init"

    try:
        run_app(link, aircraft, scenario)
    finally:
        other.close()


# ---------------------------------------------------------------------------------------------
# Command line


def test_cli_json_lines(tmp_path: Path) -> None:
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("0.0.0.0", 0))
    port = probe.getsockname()[1]
    probe.close()
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "legacy_protocol.cli",
            "--json",
            "--listen",
            str(port),
            "--count",
            "3",
            "--duration",
            "20",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
        text=True,
    )
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        deadline = time.monotonic() + 20
        seq = 0
        while proc.poll() is None and time.monotonic() < deadline:
            # Keep sending until the monitor has bound its port and seen three good datagrams.
            tx.sendto(b"\x11\x07", ("127.0.0.1", port))
            seq += 1
            tx.sendto(
                encode(IMU, vehicle_id=7, seq=seq, t_ns=1_700_000_000_123_456_789),
                ("127.0.0.1", port),
            )
            time.sleep(0.05)
        out, err = proc.communicate(timeout=10)
    finally:
        tx.close()
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    lines = [json.loads(line) for line in out.splitlines()]
    assert len(lines) == 3
    first = lines[0]
    assert first["type"] == "IMU" and first["vehicle"] == 7
    assert first["time_ns"] == 1_700_000_000_123_456_789
    assert first["fields"]["frame_count"] == 123456
    assert first["fields"]["r_rad_s"] == 0.5
    assert first["source"].startswith("127.0.0.1:")
    assert "malformed datagram" in err and "GPS is 76" in err


def test_cli_duration_stops_without_data(capsys: pytest.CaptureFixture[str]) -> None:
    t0 = time.monotonic()
    code = cli.main(["--json", "--listen", "0", "--duration", "0.3"])
    assert code == 0
    assert 0.3 <= time.monotonic() - t0 < 3
    assert capsys.readouterr().out == ""


def test_cli_argument_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["--count", "3"]) == 2
    assert "only apply with --json" in capsys.readouterr().err
    for bad, message in (
        (["--vehicle", "localhost"], "is not HOST:PORT"),
        (["--vehicle", "localhost:99999"], "outside 0..65535"),
        (["--listen", "x"], "is not a number"),
        (["--count", "0"], "must be at least 1"),
        (["--duration", "nan"], "must be above 0"),
    ):
        with pytest.raises(SystemExit) as exc:
            cli.main(bad)
        assert exc.value.code == 2
        assert message in capsys.readouterr().err


def test_cli_hooks_into_a_companion_style_parser() -> None:
    import argparse

    parser = argparse.ArgumentParser(prog="companion")
    sub = parser.add_subparsers(dest="command")
    cli.add_commands(sub)
    args = parser.parse_args(["monitor", "--listen", "6001", "--vehicle", "10.0.0.2:5600"])
    assert args.func is cli.run_monitor
    assert (args.listen, args.vehicle, args.json) == (6001, ("10.0.0.2", 5600), False)
