"""The companion beside an autopilot: its identity and the router between ground links and the
autopilot (`gcs_bridge.router`), with real parts on loopback.

A fake autopilot (a UDP socket speaking as ArduPilot's system 1, component 1) is the runtime's
`--autopilot`; two ground stations (raw UDP sockets with a pymavlink decoder, so the exact bytes
are seen) are its `--mavlink` links. Every wait is bounded.
"""

from __future__ import annotations

import select
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_for
from pymavlink.dialects.v20 import ardupilotmega as apm

from companion.core.config import Config
from companion.runtime import Runtime, RuntimeOptions
from companion.vehicle import VEHICLE, apply_device_ports, fill_device_defaults
from gcs_bridge.framing import Frame, FrameSplitter
from gcs_bridge.msg_targets import TARGETS, field_offsets, target_of
from gcs_bridge.signing import key_from_text

VEHICLE_ID = 7  # the configured id: the companion takes the autopilot's (1) once it is known
AP = (1, 1)
US = (1, 191)
GCS_A = (255, 190)
GCS_B = (254, 190)


class UdpPeer:
    """A MAVLink peer on a UDP socket: records every frame it receives (bytes and decoded),
    answers through `answer`, sends to whoever last sent to it."""

    def __init__(self, sysid: int, compid: int,
                 answer: Callable[[UdpPeer, Any], None] | None = None,
                 heartbeat: Any = None, to_port: int | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.mav = apm.MAVLink(None, sysid, compid)
        self.answer = answer
        self.heartbeat = heartbeat
        # `to_port`: a server that waits to be spoken to (mavlink-router's UDP endpoints)
        self.addr: tuple[str, int] | None = ("127.0.0.1", to_port) if to_port else None
        self.frames: list[tuple[Frame, Any]] = []
        self._lock = threading.Lock()
        self._decoder = apm.MAVLink(None)
        self._decoder.robust_parsing = True
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        next_beat = 0.0
        while not self._stop.is_set():
            r, _, _ = select.select([self.sock], [], [], 0.02)
            if r:
                data, addr = self.sock.recvfrom(65536)
                self.addr = addr
                for frame in FrameSplitter().feed(data):
                    msg = None
                    if frame.known:
                        msgs = self._decoder.parse_buffer(bytearray(frame.data)) or []
                        msg = msgs[0] if msgs else None
                    with self._lock:
                        self.frames.append((frame, msg))
                    if self.answer is not None and msg is not None:
                        self.answer(self, msg)
            if self.heartbeat is not None and self.addr and time.monotonic() >= next_beat:
                next_beat = time.monotonic() + 0.2
                self.send(self.heartbeat)

    def send(self, msg: Any) -> bytes:
        data = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) & 0xFF  # pack() leaves the sequence where it is
        return self.send_bytes(data)

    def send_bytes(self, data: bytes) -> bytes:
        assert self.addr is not None
        self.sock.sendto(data, self.addr)
        return data

    def received(self, kind: str | None = None, src: tuple[int, int] | None = None) -> list[Any]:
        with self._lock:
            frames = list(self.frames)
        return [m for f, m in frames if m is not None and (kind is None or m.get_type() == kind)
                and (src is None or (f.src_system, f.src_component) == src)]

    def raw(self) -> list[bytes]:
        with self._lock:
            return [f.data for f, _m in self.frames]

    def mark(self) -> int:
        with self._lock:
            return len(self.frames)

    def since(self, mark: int) -> list[tuple[Frame, Any]]:
        with self._lock:
            return self.frames[mark:]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.sock.close()


def autopilot_answers(peer: UdpPeer, msg: Any) -> None:
    """The fake autopilot's one service: PARAM_REQUEST_READ of TRIM_ARSPD_CM."""
    if msg.get_type() == "PARAM_REQUEST_READ" and (msg.target_system,
                                                   msg.target_component) == AP:
        peer.send(apm.MAVLink_param_value_message(b"TRIM_ARSPD_CM", 1200.0,
                                                  apm.MAV_PARAM_TYPE_INT32, 1, 0))


def companion_config(tmp: Path, endpoints: list[str], autopilot_url: str | None, *,
                     vehicle_id: int = VEHICLE_ID) -> Config:
    """The runtime's configuration: these ground links, this autopilot (None: none)."""
    cfg = fill_device_defaults(Config(), VEHICLE)
    cfg.vehicle.id = vehicle_id
    cfg.logs.dir = str(tmp / "flights")
    cfg.params.file = str(tmp / "params.parm")
    cfg.mavlink.endpoints = list(endpoints)
    if autopilot_url is not None:
        apply_device_ports(cfg, {"autopilot": autopilot_url})
    return cfg


class Running:
    """A runtime built from `cfg` (no legacy protocol, no control law), run in a thread."""

    def __init__(self, cfg: Config, *, params: dict[str, int] | None = None, **opts: Any) -> None:
        self.rt = Runtime(cfg, RuntimeOptions(legacy=False, control=False, **opts))
        for name, value in (params or {}).items():
            self.rt.ctx.params.set(name, value)
        self.runner = threading.Thread(target=self.rt.run, kwargs={"handle_signals": False},
                                       daemon=True)
        self.runner.start()

    def stop(self) -> None:
        self.rt.manager.request_stop("test")
        self.runner.join(15.0)
        assert not self.runner.is_alive()


class Rig:
    def __init__(self, tmp: Path, key_file: Path | None = None) -> None:
        self.autopilot = UdpPeer(*AP, answer=autopilot_answers,
                                 heartbeat=apm.MAVLink_heartbeat_message(
                                     apm.MAV_TYPE_FIXED_WING, apm.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                     0, 0, apm.MAV_STATE_STANDBY, 3))
        self.gcs_a = UdpPeer(*GCS_A)
        self.gcs_b = UdpPeer(*GCS_B)
        cfg = companion_config(tmp, [f"udpout:127.0.0.1:{self.gcs_a.port}",
                                     f"udpout:127.0.0.1:{self.gcs_b.port}?signing=off"],
                               f"udpout:127.0.0.1:{self.autopilot.port}")
        if key_file is not None:
            cfg.mavlink.key_file = str(key_file)
        self.running = Running(cfg)
        self.rt = self.running.rt

    def ready(self) -> None:
        """Every peer has heard the companion and the companion knows the autopilot."""
        assert wait_for(lambda: all(p.addr for p in (self.autopilot, self.gcs_a, self.gcs_b)),
                        15.0)
        assert wait_for(lambda: self.gcs_a.received("HEARTBEAT", AP)
                        and self.gcs_a.received("HEARTBEAT", US), 15.0)
        # each ground station announces itself, so the router learns where it lives
        for gcs in (self.gcs_a, self.gcs_b):
            gcs.send(apm.MAVLink_heartbeat_message(apm.MAV_TYPE_GCS, apm.MAV_AUTOPILOT_INVALID,
                                                   0, 0, 0, 3))
        assert wait_for(lambda: GCS_A in self.bridge.router.routes()
                        and GCS_B in self.bridge.router.routes(), 5.0)

    @property
    def bridge(self) -> Any:
        return self.rt.bridges[0]

    def stats(self, index: int) -> dict[str, Any]:
        return dict(self.bridge.stats()[index])

    def close(self) -> None:
        try:
            self.running.stop()
        finally:
            for p in (self.autopilot, self.gcs_a, self.gcs_b):
                p.close()


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    r = Rig(tmp_path_factory.mktemp("router"))
    try:
        r.ready()
        yield r
    finally:
        r.close()


def settle(peers: list[UdpPeer], quiet_s: float = 0.3, limit_s: float = 3.0) -> None:
    """Wait until the router had time to deliver: a bounded pause for "nothing more came"."""
    deadline = time.monotonic() + limit_s
    marks = [p.mark() for p in peers]
    while time.monotonic() < deadline:
        time.sleep(quiet_s)
        now = [p.mark() for p in peers]
        if now == marks:
            return
        marks = now


# ---------------------------------------------------------------------------- the table
def test_target_offsets_follow_the_wire_order_and_truncation() -> None:
    mav = apm.MAVLink(None, 255, 190)
    # COMMAND_LONG: floats first, then command, target_system, target_component (wire order)
    assert field_offsets(apm.MAVLink_command_long_message)["target_system"] == 30
    long_ = apm.MAVLink_command_long_message(1, 191, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    assert target_of(bytes(long_.pack(mav)), long_.id) == (1, 191)
    # MAVLink 2 drops trailing zeros: a broadcast COMMAND_LONG ends before its targets
    zero = bytes(apm.MAVLink_command_long_message(0, 0, 400, 0, 0, 0, 0, 0, 0, 0, 0).pack(mav))
    assert zero[1] < 33 and target_of(zero, long_.id) == (0, 0)
    # a target only in an extension (COMMAND_ACK's), absent from a MAVLink 1 frame: broadcast
    ack = apm.MAVLink_command_ack_message(400, 0, 0, 0, 255, 190)
    assert target_of(bytes(ack.pack(mav)), ack.id) == (255, 190)
    v1 = bytes((0xFE, 3, 0, 1, 1, ack.id)) + bytes(ack.pack(mav))[10:13] + b"\0\0"
    assert target_of(v1, ack.id) == (0, 0)
    # a system without a component (SET_MODE), and no target at all (HEARTBEAT)
    assert target_of(bytes(apm.MAVLink_set_mode_message(9, 1, 0).pack(mav)), 11) == (9, 0)
    assert apm.MAVLINK_MSG_ID_HEARTBEAT not in TARGETS
    assert len(TARGETS) > 80


# ---------------------------------------------------------------------------- identity
def test_the_ground_sees_the_autopilot_and_the_companion_as_two_components(rig: Rig) -> None:
    ap_beats = rig.gcs_a.received("HEARTBEAT", AP)
    assert ap_beats and ap_beats[-1].autopilot == apm.MAV_AUTOPILOT_ARDUPILOTMEGA
    ours = rig.gcs_a.received("HEARTBEAT", US)
    assert ours and all(b.type == apm.MAV_TYPE_ONBOARD_CONTROLLER
                        and b.autopilot == apm.MAV_AUTOPILOT_INVALID for b in ours)
    # never the vehicle: nothing of ours claims component 1, and our system is the autopilot's
    # once it is known (before that: the configured id)
    sources = {(f.src_system, f.src_component) for f, _m in rig.gcs_a.since(0)}
    assert sources <= {AP, US, (VEHICLE_ID, 191), GCS_B}, sources  # B: its HEARTBEAT
    assert not any(src[1] == 1 and src[0] == VEHICLE_ID for src in sources)
    # the configured id differs from the autopilot's: the ground is told once
    assert wait_for(lambda: [m for m in rig.gcs_a.received("STATUSTEXT", US)
                             if "autopilot is system 1, [vehicle] id is 7" in m.text], 5.0)
    # the vehicle's telemetry is the autopilot's: the companion sends none of it by default
    assert not [m for m in rig.gcs_a.received(src=US)
                if m.get_type() in ("ATTITUDE", "GLOBAL_POSITION_INT", "SYS_STATUS", "VFR_HUD")]


def test_a_parameter_read_for_the_autopilot_goes_there_untouched_and_its_answer_comes_back(
        rig: Rig) -> None:
    ap_mark = rig.autopilot.mark()
    sent = rig.gcs_a.send(apm.MAVLink_param_request_read_message(1, 1, b"TRIM_ARSPD_CM", -1))
    assert wait_for(lambda: any(f.data == sent for f, _m in rig.autopilot.since(ap_mark)), 5.0)
    assert wait_for(lambda: [m for m in rig.gcs_a.received("PARAM_VALUE", AP)
                             if m.param_id == "TRIM_ARSPD_CM"], 5.0)
    # the companion did not answer for the autopilot (no PARAM_ERROR, no value of ours)
    assert not rig.gcs_a.received("PARAM_ERROR", US)
    assert not [m for m in rig.gcs_a.received("PARAM_VALUE", US)
                if m.param_id == "TRIM_ARSPD_CM"]


def test_a_parameter_list_for_the_companion_is_answered_by_it_alone(rig: Rig) -> None:
    ap_mark = rig.autopilot.mark()
    rig.gcs_a.send(apm.MAVLink_param_request_list_message(*US))
    assert wait_for(lambda: len(rig.gcs_a.received("PARAM_VALUE", US)) >= 20, 10.0)
    values = rig.gcs_a.received("PARAM_VALUE", US)
    assert values[0].param_count == len(rig.rt.ctx.params.specs())
    settle([rig.autopilot])
    asked = [m for _f, m in rig.autopilot.since(ap_mark)
             if m is not None and m.get_type() == "PARAM_REQUEST_LIST"]
    assert asked == []  # addressed to 191: the autopilot never sees it


def test_a_parameter_list_for_the_autopilot_is_not_answered_by_the_companion(rig: Rig) -> None:
    ap_mark, gcs_mark = rig.autopilot.mark(), rig.gcs_a.mark()
    sent = rig.gcs_a.send(apm.MAVLink_param_request_list_message(*AP))
    assert wait_for(lambda: any(f.data == sent for f, _m in rig.autopilot.since(ap_mark)), 5.0)
    settle([rig.gcs_a])
    assert not [m for f, m in rig.gcs_a.since(gcs_mark)
                if m is not None and m.get_type() == "PARAM_VALUE"
                and (f.src_system, f.src_component) == US]


def test_a_frame_for_an_unknown_component_is_dropped_counted_and_named(rig: Rig) -> None:
    ap_mark = rig.autopilot.mark()
    dropped = rig.stats(0)["routed_dropped"]
    rig.gcs_a.send(apm.MAVLink_command_long_message(1, 77, apm.MAV_CMD_DO_SET_SERVO, 0,
                                                    5, 1500, 0, 0, 0, 0, 0))
    assert wait_for(lambda: rig.stats(0)["routed_dropped"] == dropped + 1, 5.0)
    assert wait_for(lambda: [m for m in rig.gcs_a.received("STATUSTEXT", US)
                             if "for 1/77" in m.text], 5.0)
    settle([rig.autopilot, rig.gcs_b])
    assert not [m for f, m in rig.autopilot.since(ap_mark) if m is not None
                and m.get_type() == "COMMAND_LONG" and (f.src_system, f.src_component) == GCS_A]
    assert not [m for m in rig.gcs_b.received("COMMAND_LONG") if m.target_component == 77]


def test_a_signed_frame_arrives_untouched(rig: Rig) -> None:
    signer = apm.MAVLink(None, *GCS_B)
    signer.signing.secret_key = key_from_text("a key the companion does not hold")
    signer.signing.link_id = 3
    signer.signing.sign_outgoing = True
    signer.signing.timestamp = 123456789
    data = bytes(apm.MAVLink_param_request_read_message(1, 1, b"TRIM_ARSPD_CM", -1)
                 .pack(signer))
    assert data[2] & 0x01  # signed
    ap_mark = rig.autopilot.mark()
    rig.gcs_b.send_bytes(data)  # link 1 has signing off: the frame is forwarded as it is
    assert wait_for(lambda: data in [f.data for f, _m in rig.autopilot.since(ap_mark)], 5.0)


def test_nothing_goes_back_to_its_source_and_a_broadcast_command_reaches_the_autopilot_once(
        rig: Rig) -> None:
    ap_mark, a_mark, b_mark = rig.autopilot.mark(), rig.gcs_a.mark(), rig.gcs_b.mark()
    cmd = rig.gcs_a.send(apm.MAVLink_command_long_message(0, 0, apm.MAV_CMD_DO_SET_MODE, 0,
                                                          1, 10, 0, 0, 0, 0, 0))
    assert wait_for(lambda: any(f.data == cmd for f, _m in rig.autopilot.since(ap_mark)), 5.0)
    assert wait_for(lambda: any(f.data == cmd for f, _m in rig.gcs_b.since(b_mark)), 5.0)
    settle([rig.autopilot, rig.gcs_a, rig.gcs_b])
    assert [f.data for f, _m in rig.autopilot.since(ap_mark)].count(cmd) == 1
    assert [f.data for f, _m in rig.gcs_b.since(b_mark)].count(cmd) == 1
    # never back to the ground station that sent it, nor the autopilot's frames to the autopilot
    assert not [f for f, _m in rig.gcs_a.since(0) if (f.src_system, f.src_component) == GCS_A]
    assert not [f for f, _m in rig.autopilot.since(0) if (f.src_system, f.src_component) == AP]
    # the companion does not acknowledge a command for every component that it does not know
    assert not [m for f, m in rig.gcs_a.since(a_mark) if m is not None
                and m.get_type() == "COMMAND_ACK" and (f.src_system, f.src_component) == US]


def test_a_frame_for_one_ground_station_goes_to_it_only(rig: Rig) -> None:
    # the autopilot answers ground station B: A never sees it
    a_mark, b_mark = rig.gcs_a.mark(), rig.gcs_b.mark()
    ack = rig.autopilot.send(apm.MAVLink_command_ack_message(
        apm.MAV_CMD_DO_SET_MODE, 0, 0, 0, *GCS_B))
    assert wait_for(lambda: any(f.data == ack for f, _m in rig.gcs_b.since(b_mark)), 5.0)
    settle([rig.gcs_a])
    assert not any(f.data == ack for f, _m in rig.gcs_a.since(a_mark))


def test_routing_counters_are_in_the_stats_and_the_summary(rig: Rig) -> None:
    st = rig.stats(0)
    assert st["routed_forwarded_in"] >= 3 and st["routed_forwarded_out"] > 10
    threads = {t.name: t for t in rig.rt.manager.threads}
    c = threads["mavroute"].counters()
    assert c["from_autopilot"] > 10 and c["forwarded_to_autopilot"] >= 3


def test_without_an_autopilot_the_bridge_is_the_vehicle_as_before(tmp_path: Path) -> None:
    gcs = UdpPeer(*GCS_A)
    running = Running(companion_config(tmp_path, [f"udpout:127.0.0.1:{gcs.port}"], None),
                      estimator=False)
    rt = running.rt
    try:
        assert wait_for(lambda: gcs.received("HEARTBEAT"), 10.0)
        assert rt.manager.find("mavroute") is None
    finally:
        running.stop()
        gcs.close()
    beat = gcs.received("HEARTBEAT")[0]
    assert (beat.get_srcSystem(), beat.get_srcComponent()) == (VEHICLE_ID, 1)
    assert (beat.type, beat.autopilot) == (apm.MAV_TYPE_FIXED_WING, apm.MAV_AUTOPILOT_GENERIC)
    assert "routed_dropped" not in rt.bridges[0].stats()[0]


def test_an_autopilot_endpoint_needs_an_autopilot(tmp_path: Path) -> None:
    from gcs_bridge.transports.endpoints import EndpointError

    cfg = companion_config(tmp_path, ["autopilot:"], None)
    with pytest.raises(EndpointError, match="--autopilot URL"):
        Runtime(cfg, RuntimeOptions(legacy=False, control=False, estimator=False))


def test_a_radio_budget_saves_up_half_a_second_and_refuses_beyond() -> None:
    from gcs_bridge.router import ByteBudget

    budget = ByteBudget(1000.0)  # bytes/s: 500 may be saved up
    assert budget.take(280) and budget.take(200)
    assert not budget.take(280)  # 20 left
    budget._at_s -= 0.3  # 0.3 s later: 300 more
    assert budget.take(280) and not budget.take(100)
