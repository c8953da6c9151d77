"""Horizon estimates reach the estimator's slot through both links: legacy UDP and MAVLink."""

from __future__ import annotations

import math
import threading

from conftest import free_udp_port, wait_for

from companion.core.clock import Clock
from companion.core.params import ParamRegistry
from companion.watchdog import RuntimeContext, ThreadManager
from gcs_bridge import MavlinkBridge
from horizon.estimate import HorizonEstimate
from horizon.stream import LegacyHorizonSender, MavlinkHorizonSender
from legacy_protocol.adapter import LegacyAdapter


def estimate(roll_deg: float, pitch_deg: float, quality: float) -> HorizonEstimate:
    return HorizonEstimate(True, quality, "robust", 320, 240, (0.0, 120.0), (320.0, 120.0),
                           roll_deg, 0.0, pitch_deg)


def test_horizon_reaches_the_estimator_slot_by_legacy_and_mavlink() -> None:
    ctx = RuntimeContext(clock=Clock(), params=ParamRegistry())
    mgr = ThreadManager(ctx, [])
    legacy_port = free_udp_port()
    mav_port = free_udp_port()
    adapter = LegacyAdapter(ctx, mgr, dest=f"127.0.0.1:{free_udp_port()}",
                            listen_port=legacy_port, bind_host="127.0.0.1")
    bridge = MavlinkBridge(ctx, mgr, endpoints=[f"udpin:127.0.0.1:{mav_port}"], tlog=False)
    runner = threading.Thread(target=mgr.run)
    mgr.start()
    runner.start()
    legacy = LegacyHorizonSender("127.0.0.1", legacy_port, vehicle_id=1)
    mav = MavlinkHorizonSender(f"udpout:127.0.0.1:{mav_port}")
    try:
        legacy(estimate(10.0, 2.0, 0.9), ctx.clock.realtime_ns())
        assert wait_for(lambda: ctx.state.horizon.read() is not None, 5.0)
        h = ctx.state.horizon.read()
        assert h is not None and h.source == "legacy"
        assert math.isclose(h.roll_rad, math.radians(10.0), abs_tol=1e-6)
        assert math.isclose(h.quality, 0.9, abs_tol=1e-6)
        for _ in range(50):  # the bridge learns the sender from its first datagrams
            mav(estimate(-20.0, 3.0, 0.7), ctx.clock.realtime_ns())
            if wait_for(lambda: (s := ctx.state.horizon.read()) is not None and s.source == "mavlink", 0.1):
                break
        h = ctx.state.horizon.read()
        assert h is not None and h.source == "mavlink"
        assert math.isclose(h.roll_rad, math.radians(-20.0), abs_tol=1e-5)
        assert math.isclose(h.pitch_rad, math.radians(3.0), abs_tol=1e-5)
        assert math.isclose(h.quality, 0.7, abs_tol=1e-6)
    finally:
        legacy.close()
        mav.close()
        mgr.request_stop()
        runner.join(5)
        mgr.shutdown()
        bridge.close()
        adapter.close()
