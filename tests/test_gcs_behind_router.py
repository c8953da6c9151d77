"""The companion as one endpoint of the user's MAVLink router (marked `router`: the real
mavlink-routerd, MAVLINK_ROUTER names it).

mavlink-router runs on loopback with three UDP server endpoints (its README's setup, the
configuration written to a temporary directory, TCP off): the autopilot's (a fake ArduPilot, as
in tests/test_gcs_router.py), the companion's and a ground station's. The companion runs
`--autopilot udpout:<its endpoint>` and `--mavlink autopilot:`: one connection carries the
autopilot link and the companion's component, mavlink-router routes, the companion does not.
"""

from __future__ import annotations

import subprocess
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import free_udp_port, peer_tool, wait_for
from pymavlink.dialects.v20 import ardupilotmega as apm
from test_gcs_router import (
    AP,
    GCS_A,
    US,
    Running,
    UdpPeer,
    autopilot_answers,
    companion_config,
    settle,
)

pytestmark = pytest.mark.router

CONF = """[General]
TcpServerPort = 0
ReportStats = false
DebugLogLevel = info
{endpoints}"""
ENDPOINT = """
[UdpEndpoint {name}]
Mode = Server
Address = 127.0.0.1
Port = {port}
"""


class RouterRig:
    def __init__(self, tmp: Path) -> None:
        binary = peer_tool("router")
        assert binary is not None
        ports = {name: free_udp_port() for name in ("fc", "companion", "gcs")}
        conf = tmp / "router.conf"
        conf.write_text(CONF.format(endpoints="".join(
            ENDPOINT.format(name=n, port=p) for n, p in ports.items())))
        (tmp / "conf.d").mkdir()
        self.log = open(tmp / "mavlink-router.out", "wb")  # noqa: SIM115 (closed in close)
        self.proc = subprocess.Popen([binary, "-c", str(conf), "-d", str(tmp / "conf.d")],
                                     stdout=self.log, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL)
        self.autopilot = UdpPeer(*AP, answer=autopilot_answers, to_port=ports["fc"],
                                 heartbeat=apm.MAVLink_heartbeat_message(
                                     apm.MAV_TYPE_FIXED_WING, apm.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                     0, 0, apm.MAV_STATE_STANDBY, 3))
        self.gcs = UdpPeer(*GCS_A, to_port=ports["gcs"], heartbeat=apm.MAVLink_heartbeat_message(
            apm.MAV_TYPE_GCS, apm.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))
        self.running = Running(companion_config(
            tmp, ["autopilot:"], f"udpout:127.0.0.1:{ports['companion']}", vehicle_id=1))
        self.rt = self.running.rt

    def close(self) -> None:
        try:
            self.running.stop()
        finally:
            for peer in (self.autopilot, self.gcs):
                peer.close()
            self.proc.terminate()
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
            self.log.close()


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RouterRig]:
    r = RouterRig(tmp_path_factory.mktemp("behind-router"))
    try:
        assert wait_for(lambda: r.gcs.received("HEARTBEAT", AP)
                        and r.gcs.received("HEARTBEAT", US)
                        and all(t.running for t in r.rt.manager.threads), 15.0)
        yield r
    finally:
        r.close()


def test_the_ground_sees_both_components_once_each(rig: RouterRig) -> None:
    assert rig.rt.bridges[0].router is None  # mavlink-router routes, the companion does not
    assert rig.rt.manager.find("mavroute") is None
    ours = rig.gcs.received("HEARTBEAT", US)
    assert all(b.type == apm.MAV_TYPE_ONBOARD_CONTROLLER for b in ours)
    mark = rig.gcs.mark()
    rig.gcs.send(apm.MAVLink_param_request_list_message(*US))
    assert wait_for(lambda: len(rig.gcs.since(mark)) > 100, 10.0)
    settle([rig.gcs])
    # no duplicates, no loops: no frame of the autopilot's (its sequence numbers run) and no
    # parameter of the companion's arrives twice
    from_ap = Counter(f.data for f, _m in rig.gcs.since(0) if (f.src_system, f.src_component) == AP)
    assert from_ap and max(from_ap.values()) == 1
    indices = Counter(m.param_index for m in rig.gcs.received("PARAM_VALUE", US))
    assert len(indices) > 20 and max(indices.values()) == 1
    # one HEARTBEAT a second for the companion: the autopilot link's (the bridge's own is off
    # on an `autopilot:` link, so two do not interleave their sequence numbers)
    beats = [m for m in rig.gcs.received("HEARTBEAT", US)]
    assert beats and all(b.system_status == apm.MAV_STATE_ACTIVE for b in beats)


def test_parameters_go_to_the_component_they_are_for(rig: RouterRig) -> None:
    ap_mark, gcs_mark = rig.autopilot.mark(), rig.gcs.mark()
    rig.gcs.send(apm.MAVLink_param_request_list_message(*US))
    assert wait_for(lambda: len([m for f, m in rig.gcs.since(gcs_mark)
                                 if m is not None and m.get_type() == "PARAM_VALUE"
                                 and (f.src_system, f.src_component) == US]) >= 20, 10.0)
    rig.gcs.send(apm.MAVLink_param_request_read_message(*AP, b"TRIM_ARSPD_CM", -1))
    assert wait_for(lambda: [m for m in rig.gcs.received("PARAM_VALUE", AP)
                             if m.param_id == "TRIM_ARSPD_CM"], 5.0)
    settle([rig.autopilot])
    kinds = [m.get_type() for f, m in rig.autopilot.since(ap_mark)
             if m is not None and (f.src_system, f.src_component) == GCS_A]
    assert "PARAM_REQUEST_READ" in kinds and "PARAM_REQUEST_LIST" not in kinds


def test_the_autopilot_link_and_a_broadcast_command_pass_the_router(rig: RouterRig) -> None:
    # the autopilot link's own requests reach the autopilot through mavlink-router
    assert wait_for(lambda: [m for m in rig.autopilot.received("COMMAND_LONG", US)
                             if m.command == apm.MAV_CMD_SET_MESSAGE_INTERVAL], 10.0)
    ap_mark, gcs_mark = rig.autopilot.mark(), rig.gcs.mark()
    cmd = rig.gcs.send(apm.MAVLink_command_long_message(0, 0, apm.MAV_CMD_DO_SET_MODE, 0,
                                                        1, 10, 0, 0, 0, 0, 0))
    assert wait_for(lambda: cmd in [f.data for f, _m in rig.autopilot.since(ap_mark)], 5.0)
    settle([rig.autopilot, rig.gcs])
    assert [f.data for f, _m in rig.autopilot.since(ap_mark)].count(cmd) == 1
    assert not [m for f, m in rig.gcs.since(gcs_mark) if m is not None
                and m.get_type() == "COMMAND_ACK" and (f.src_system, f.src_component) == US]
