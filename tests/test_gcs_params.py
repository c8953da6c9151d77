"""The MAVLink parameter protocol with a raw MAVLink 2 client, against a SyntheticVehicle.

Every test runs the MAVLink bridge on a `support.synthetic_vehicle.SyntheticVehicle`: synthetic
vehicle state (an aircraft in a steady banked circle) under a real ThreadManager, in this
process. No drivers, estimator, control law or simulator run, and the parameters are only
the manager's, the synthetic threads' and the bridge's (not the runtime's set) plus the
test's.
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from conftest import free_udp_port, wait_for
from support.synthetic_vehicle import MiniGcs, SyntheticVehicle

from companion.core.params import ParamType, float_param, int_param, to_float32
from gcs_bridge.dialect import mavlink
from gcs_bridge.params import codec as param_codec

EXTRA = [
    int_param("TST_BIG", 0, -(2**31), 2**31 - 1, "", "full int32 range"),
    float_param("TST_F", 1.5, -10.0, 10.0, "m", "a float"),
    int_param("TST_RO", 3, 0, 10, "", "read-only", read_only=True),
    int_param("TST_BOOT", 0, 0, 5, "", "needs a restart", reboot=True),
]


@contextmanager
def running(tmp_path: Path | None = None, identity: str = "generic",
            **kwargs: Any) -> Iterator[tuple[SyntheticVehicle, MiniGcs]]:
    gcs = MiniGcs(listen_port=free_udp_port())
    params_file = tmp_path / "params.parm" if tmp_path is not None else None
    try:
        with SyntheticVehicle([f"udpout:127.0.0.1:{gcs.port}?identity={identity}"],
                              extra_params=EXTRA,
                              params_file=params_file, **kwargs) as v:
            assert gcs.recv(5.0, "HEARTBEAT") is not None
            yield v, gcs
    finally:
        gcs.close()


def param_set(gcs: MiniGcs, name: str, raw: bytes, ptype: int, target_comp: int = 1) -> None:
    msg = mavlink.MAVLink_param_set_message(1, target_comp, name.encode(), 0.0, ptype)
    msg.param_value = struct.unpack("<f", raw)[0]

    # pack the raw bytes ourselves: a Python float would quieten a signalling NaN
    def pack(mav: mavlink.MAVLink, force_mavlink1: bool = False) -> bytes:
        payload = struct.pack("<4sBB16sB", raw, 1, target_comp, name.encode(), ptype)
        return msg._pack(mav, msg.crc_extra, payload)

    msg.pack = pack  # type: ignore[method-assign]
    gcs.send(msg)


def value_of(gcs: MiniGcs, name: str, timeout_s: float = 2.0) -> Any:
    return gcs.recv(timeout_s, "PARAM_VALUE", lambda m: m.param_id == name)


def test_list_read_and_targeting() -> None:
    with running() as (v, gcs):
        names = [s.name for s in v.params.specs()]
        gcs.send(mavlink.MAVLink_param_request_list_message(1, 1))
        seen: dict[int, Any] = {}
        while len(seen) < len(names):
            m = gcs.recv(3.0, "PARAM_VALUE")
            assert m is not None, f"list stopped after {len(seen)} of {len(names)}"
            seen[m.param_index] = m
        assert sorted(seen) == list(range(len(names)))
        assert all(m.param_count == len(names) for m in seen.values())
        assert [seen[i].param_id for i in range(len(names))] == names
        for i, spec in enumerate(v.params.specs()):
            assert seen[i].param_type == spec.ptype.mav_type
            raw = param_codec.raw_value_of(seen[i])
            expected = v.params.get(spec.name)
            if spec.ptype is ParamType.FLOAT32:
                expected = to_float32(expected)
            assert param_codec.decode(raw, spec.ptype.mav_type, bytewise=True) == expected
        # by name, addressed to component 0 (all) and to our component 1
        gcs.send(mavlink.MAVLink_param_request_read_message(1, 0, b"TST_F", -1))
        m = value_of(gcs, "TST_F")
        assert m is not None and m.param_value == 1.5 and m.param_index == names.index("TST_F")
        gcs.send(mavlink.MAVLink_param_request_read_message(1, 1, b"", names.index("TST_RO")))
        assert value_of(gcs, "TST_RO") is not None
        # another component, another vehicle: not for us
        gcs.send(mavlink.MAVLink_param_request_read_message(1, 50, b"TST_F", -1))
        gcs.send(mavlink.MAVLink_param_request_read_message(9, 1, b"TST_F", -1))
        assert value_of(gcs, "TST_F", 0.4) is None
        gcs.send(mavlink.MAVLink_param_request_read_message(1, 1, b"NOPE_NOPE", -1))
        err = gcs.recv(2.0, "PARAM_ERROR")
        assert err is not None and err.error == mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST
        assert (err.param_id, err.target_system, err.target_component) == ("NOPE_NOPE", 255, 190)
        gcs.send(mavlink.MAVLink_param_request_read_message(1, 1, b"", 10_000))
        assert gcs.recv(2.0, "PARAM_ERROR").param_index == 10_000


def test_set_keeps_the_raw_bytes_and_takes_effect(tmp_path: Path) -> None:
    with running(tmp_path) as (v, gcs):
        source = v.sources[0]
        calls = source.on_params_changed_calls
        # 0x7F800001 is a signalling NaN as a float: it must arrive and come back unchanged
        raw = struct.pack("<i", 0x7F800001)
        param_set(gcs, "TST_BIG", raw, param_codec.T_INT32)
        m = value_of(gcs, "TST_BIG")
        assert m is not None and param_codec.raw_value_of(m) == raw
        assert v.params.get("TST_BIG") == 0x7F800001
        param_set(gcs, "TST_F", struct.pack("<f", 3.5), param_codec.T_REAL32, target_comp=0)
        assert value_of(gcs, "TST_F").param_value == 3.5
        # a change is told to the thread that owns the parameter, and only to it
        assert source.on_params_changed_calls == calls
        own = f"{source.param_prefix}_MSG_MS"
        param_set(gcs, own, struct.pack("<i", 500), param_codec.T_INT32)
        assert value_of(gcs, own).param_value is not None
        assert wait_for(lambda: source.on_params_changed_calls > calls, 2.0), "owner not told"
        # persisted once the changes pause, without waiting for the shutdown
        path = tmp_path / "params.parm"
        assert wait_for(lambda: path.exists() and "TST_F" in path.read_text()
                        and "3.5" in path.read_text(), 5.0)
        # setting the same value again is still answered (on this link)
        param_set(gcs, "TST_F", struct.pack("<f", 3.5), param_codec.T_REAL32)
        assert value_of(gcs, "TST_F").param_value == 3.5
    # a new run loads the saved values
    with running(tmp_path) as (v2, _gcs):
        assert v2.params.get("TST_F") == 3.5 and v2.params.get("TST_BIG") == 0x7F800001


def test_refused_sets_answer_old_value_reason_and_error() -> None:
    with running() as (v, gcs):
        cases = [
            ("TST_F", struct.pack("<f", 20.0), param_codec.T_REAL32, "out of range",
             mavlink.MAV_PARAM_ERROR_VALUE_OUT_OF_RANGE),
            ("TST_RO", struct.pack("<i", 5), param_codec.T_INT32, "read-only",
             mavlink.MAV_PARAM_ERROR_READ_ONLY),
            ("TST_BIG", struct.pack("<f", 2.5), param_codec.T_REAL32, "not an integer", 7),
            ("TST_F", struct.pack("<i", 2), param_codec.T_INT32, "wrong type", 7),
            ("TST_BIG", struct.pack("<i", 2), mavlink.MAV_PARAM_TYPE_INT64, "wrong type", 7),
            ("NOPE_X", struct.pack("<i", 2), param_codec.T_INT32, "unknown parameter",
             mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST),
            # the watchdog granularity may not exceed the shortest watchdog period (500 ms)
            ("MGR_WDG_GRAN_MS", struct.pack("<i", 900), param_codec.T_INT32, "exceeds",
             mavlink.MAV_PARAM_ERROR_VALUE_OUT_OF_RANGE),
            # and no watchdog period may be shorter than the granularity (set to 50 ms below):
            # the rule the legacy protocol always had, now the registry's, so MAVLink refuses it
            ("IMU_WDG_MS", struct.pack("<i", 20), param_codec.T_INT32, "below MGR_WDG_GRAN_MS", mavlink.MAV_PARAM_ERROR_VALUE_OUT_OF_RANGE),
        ]
        v.params.set("MGR_WDG_GRAN_MS", 50)
        for name, raw, ptype, reason, code in cases:
            before = v.params.get(name) if name in v.params else None
            param_set(gcs, name, raw, ptype)
            err = gcs.recv(2.0, "PARAM_ERROR", lambda m, n=name: m.param_id == n)
            assert err is not None and err.error == code, name
            text = gcs.recv(2.0, "STATUSTEXT", lambda m, n=name: m.text.startswith(n))
            assert text is not None and reason in text.text, text
            assert text.severity == mavlink.MAV_SEVERITY_WARNING
            if before is not None:
                m = value_of(gcs, name)
                assert m is not None
                assert param_codec.decode(param_codec.raw_value_of(m), m.param_type,
                                          bytewise=True) == before
                assert v.params.get(name) == before


def test_changes_made_elsewhere_are_announced_to_every_link() -> None:
    gcs_a = MiniGcs(listen_port=free_udp_port())
    gcs_b = MiniGcs(listen_port=free_udp_port())
    try:
        with SyntheticVehicle([f"udpout:127.0.0.1:{gcs_a.port}", f"udpout:127.0.0.1:{gcs_b.port}"],
                              extra_params=EXTRA) as v:
            assert gcs_a.recv(5.0, "HEARTBEAT") and gcs_b.recv(5.0, "HEARTBEAT")
            # the legacy monitor's bridge changes parameters through the registry, from its
            # own thread: both ground stations hear of it
            t = threading.Thread(target=v.params.set, args=("TST_F", -4.25))
            t.start()
            t.join()
            for gcs in (gcs_a, gcs_b):
                m = value_of(gcs, "TST_F")
                assert m is not None and m.param_value == -4.25
            # and a set from one ground station reaches the other one
            param_set(gcs_a, "TST_BIG", struct.pack("<i", -123456789), param_codec.T_INT32)
            m = value_of(gcs_b, "TST_BIG")
            assert m is not None and struct.unpack("<i", param_codec.raw_value_of(m))[0] == -123456789
    finally:
        gcs_a.close()
        gcs_b.close()


def test_c_cast_identity_round_trips_integers() -> None:
    with running(identity="ardupilot") as (v, gcs):
        hb = gcs.recv(2.0, "HEARTBEAT")
        assert hb.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
        param_set(gcs, "TST_BIG", struct.pack("<f", 1234567.0), param_codec.T_INT32)
        m = value_of(gcs, "TST_BIG")
        assert m is not None and m.param_value == 1234567.0
        assert v.params.get("TST_BIG") == 1234567


def test_a_parameter_that_needs_a_restart_says_so() -> None:
    with running() as (v, gcs):
        param_set(gcs, "TST_BOOT", struct.pack("<i", 2), param_codec.T_INT32)
        assert value_of(gcs, "TST_BOOT") is not None and v.params.get("TST_BOOT") == 2
        text = gcs.seen(2.0, "STATUSTEXT", lambda m: m.text.startswith("TST_BOOT"))
        assert text is not None and "next start" in text.text


def test_no_ground_station_can_switch_off_the_link_it_talks_through(tmp_path: Path) -> None:
    """The fault campaign's finding: a PARAM_SET storm on an unsigned link set MAV0RX_ENABLE to
    0, the receive thread stopped, and the aircraft was deaf to every ground station, also after
    a restart, because the value was persisted. The link threads' ENABLE is now read-only, and a
    read-only value in a parameter file is ignored (the configuration decides)."""
    with running(tmp_path) as (v, gcs):
        for name in ("MAV0RX_ENABLE", "MAV0TX_ENABLE"):
            param_set(gcs, name, struct.pack("<i", 0), param_codec.T_INT32)
            err = gcs.recv(2.0, "PARAM_ERROR", lambda m, n=name: m.param_id == n)
            assert err is not None and err.error == mavlink.MAV_PARAM_ERROR_READ_ONLY, name
            assert v.params.get(name) == 1
        # still listening: a read answers
        gcs.send(mavlink.MAVLink_param_request_read_message(1, 1, b"MAV0RX_ENABLE", -1))
        m = value_of(gcs, "MAV0RX_ENABLE")
        assert m is not None
    # an earlier attack's file: the value is not applied on the next start
    (tmp_path / "params.parm").write_text("MAV0RX_ENABLE 0\nTST_F 2.5\n", encoding="utf-8")
    with running(tmp_path) as (v, gcs):
        assert v.params.get("MAV0RX_ENABLE") == 1
        assert v.params.get("TST_F") == 2.5
        gcs.send(mavlink.MAVLink_param_request_read_message(1, 1, b"TST_F", -1))
        assert value_of(gcs, "TST_F") is not None
