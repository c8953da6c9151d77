"""pymavlink's own client API (`mavutil`), as ground-station scripts use it, against the bridge.

Every test runs the MAVLink bridge on a `support.synthetic_vehicle.SyntheticVehicle`: synthetic
vehicle state (an aircraft in a steady banked circle) under a real ThreadManager, in this
process. No drivers, estimator, control law or simulator run, and the parameters are only
the manager's, the synthetic threads' and the bridge's (not the runtime's set) plus the
test's.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import free_udp_port, wait_for
from pymavlink import mavutil
from support.synthetic_vehicle import SyntheticVehicle

from companion.core.params import float_param, int_param
from gcs_bridge.signing import new_key_file

EXTRA = [
    int_param("TST_BIG", 0, -(2**31), 2**31 - 1, "", "full int32 range"),
    float_param("TST_F", 1.5, -10.0, 10.0, "m", "a float"),
]


@pytest.fixture
def mavlink2(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """mavutil picks MAVLink 2 from the environment; keep that to this test."""
    monkeypatch.setenv("MAVLINK20", "1")
    mavutil.set_dialect("common")
    yield
    monkeypatch.delenv("MAVLINK20")
    mavutil.set_dialect("common")


def connect(port: int) -> mavutil.mavfile:
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=255,
                                      source_component=190, dialect="common")
    assert conn.wait_heartbeat(timeout=5) is not None
    return conn


def test_mavutil_fetch_set_and_command(mavlink2: None) -> None:
    port = free_udp_port()
    with SyntheticVehicle([f"udpout:127.0.0.1:{port}"], extra_params=EXTRA, vehicle_id=4) as v:
        conn = connect(port)
        try:
            assert conn.target_system == 4  # its requests go to component 0: all components
            conn.param_fetch_all()
            names: set[str] = set()
            while len(names) < len(v.params):
                m = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=3)
                assert m is not None, f"got {len(names)} of {len(v.params)}"
                names.add(m.param_id)
            assert names == {s.name for s in v.params.specs()}
            # mavutil sends every value as REAL32; an integral one is accepted for an int
            conn.param_set_send("TST_BIG", 77.0)
            conn.param_set_send("TST_F", -1.25)
            assert wait_for(lambda: v.params.get("TST_BIG") == 77 and v.params.get("TST_F") == -1.25, 3.0)
            conn.mav.command_long_send(4, 1, mavutil.mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                       mavutil.mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION,
                                       0, 0, 0, 0, 0, 0)
            ack = conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=3)
            assert ack is not None and ack.result == mavutil.mavlink.MAV_RESULT_ACCEPTED
            ver = conn.recv_match(type="AUTOPILOT_VERSION", blocking=True, timeout=3)
            assert ver is not None and ver.uid == 4
        finally:
            conn.close()


def test_mavutil_signing(mavlink2: None, tmp_path: Path) -> None:
    port = free_udp_port()
    key_file = tmp_path / "mavlink.key"
    passphrase = new_key_file(key_file)
    with SyntheticVehicle([f"udpout:127.0.0.1:{port}"], extra_params=EXTRA, key_file=key_file) as v:
        conn = connect(port)
        try:
            conn.param_set_send("TST_F", 2.0)  # unsigned: refused
            assert wait_for(lambda: v.bridge.stats()[0]["refused"] == 1, 3.0)
            assert v.params.get("TST_F") == 1.5
            conn.setup_signing(hashlib.sha256(passphrase.encode()).digest(), sign_outgoing=True)
            conn.param_set_send("TST_F", 2.0)
            assert wait_for(lambda: v.params.get("TST_F") == 2.0, 3.0)
            m = conn.recv_match(type="PARAM_VALUE", blocking=True, timeout=3)
            assert m is not None and m.get_signed()  # our answers verify with the key
        finally:
            conn.close()
