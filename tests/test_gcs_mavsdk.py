"""MAVSDK 4.1 (the native Python binding) against the bridge on a SyntheticVehicle, over UDP.

Every test runs the MAVLink bridge on a `support.synthetic_vehicle.SyntheticVehicle`: synthetic
vehicle state (an aircraft in a steady banked circle) under a real ThreadManager, in this
process. No drivers, estimator, control law or simulator run, and the parameters are only
the manager's, the synthetic threads' and the bridge's (not the runtime's set) plus the
test's.

MAVSDK against a whole `companion sim` flight is in test_gcs_clients_sim.py.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from conftest import free_udp_port, quiet_mavsdk, wait_for
from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.plugins.param.param import Param, ParamError, ParamResult
from mavsdk.plugins.telemetry.telemetry import Telemetry
from support.synthetic_vehicle import ORIGIN, SyntheticVehicle, circle_state

from companion.core.params import ParamType, float_param, int_param, to_float32

EXTRA = [
    int_param("TST_BIG", 0, -(2**31), 2**31 - 1, "", "full int32 range"),
    float_param("TST_F", 1.5, -10.0, 10.0, "m", "a float"),
]


@pytest.fixture(scope="module", autouse=True)
def _mavsdk_quiet() -> Iterator[None]:
    with quiet_mavsdk():
        yield


@contextmanager
def mavsdk_on(port: int) -> Iterator[Any]:
    sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        sdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = sdk.first_autopilot(5.0)
        assert system is not None, "MAVSDK did not discover the vehicle"
        yield system
    finally:
        sdk.destroy()


def test_discover_and_telemetry() -> None:
    port = free_udp_port()
    with SyntheticVehicle([f"udpout:127.0.0.1:{port}"], vehicle_id=3) as v, mavsdk_on(port) as system:
        assert system.get_system_id() == 3 and system.has_autopilot()
        v.params.set("EST_MSG_MS", 50)
        telemetry = Telemetry(system)
        attitude: list[Any] = []
        position: list[Any] = []
        lock = threading.Lock()

        def keep(store: list[Any]) -> Any:
            def cb(value: Any, *_: Any) -> None:
                with lock:
                    store.append(value)
            return cb

        telemetry.subscribe_attitude_euler(keep(attitude))
        telemetry.subscribe_position(keep(position))
        assert wait_for(lambda: len(attitude) >= 5 and len(position) >= 5, 5.0)
        with lock:
            a, p = attitude[-1], position[-1]
        circle = circle_state(0.0)  # the synthetic aircraft flies a steady banked circle
        assert abs(a.roll_deg - math.degrees(circle["roll"])) < 0.1
        assert abs(a.pitch_deg - math.degrees(circle["pitch"])) < 0.1
        assert abs(p.latitude_deg - ORIGIN[0]) < 0.01 and abs(p.longitude_deg - ORIGIN[1]) < 0.01
        assert abs(p.relative_altitude_m - 100.0) < 0.5
        # MAVSDK asks for rates with MAV_CMD_SET_MESSAGE_INTERVAL
        telemetry.set_rate_attitude_euler(20.0)
        assert v.bridge.links[0].interval_us(30) == 50_000


def test_every_parameter_get_set_list_and_refusals(tmp_path: Path) -> None:
    port = free_udp_port()
    params_file = tmp_path / "params.parm"
    with SyntheticVehicle([f"udpout:127.0.0.1:{port}"], extra_params=EXTRA,
                          params_file=params_file) as v, mavsdk_on(port) as system:
        param = Param(system)
        everything = param.get_all_params()
        ints = {p.name: p.value for p in everything.int_params}
        floats = {p.name: p.value for p in everything.float_params}
        assert len(ints) + len(floats) == len(v.params)
        for spec in v.params.specs():
            value = v.params.get(spec.name)
            if spec.ptype is ParamType.INT32:
                assert ints[spec.name] == value
                assert param.get_param_int(spec.name) == value
            else:
                assert floats[spec.name] == to_float32(value)
                assert param.get_param_float(spec.name) == to_float32(value)
        # integers beyond 2**24 and negative ones need the bytewise encoding to survive
        for value in (123_456_789, -987_654_321, 2**31 - 1):
            param.set_param_int("TST_BIG", value)
            assert v.params.get("TST_BIG") == value
            assert param.get_param_int("TST_BIG") == value
        param.set_param_float("TST_F", -3.25)
        assert v.params.get("TST_F") == -3.25
        param.set_param_int("IMU_MSG_MS", 200)
        assert v.params.get("IMU_MSG_MS") == 200
        # refusals: out of range, unknown, wrong type; nothing changes
        with pytest.raises(ParamError) as info:
            param.set_param_float("TST_F", 20.0)
        assert info.value.result == ParamResult.VALUE_OUT_OF_RANGE
        with pytest.raises(ParamError) as info:
            param.set_param_int("NOPE_NOPE", 1)
        assert info.value.result == ParamResult.DOES_NOT_EXIST
        with pytest.raises(ParamError):
            param.set_param_float("IMU_MSG_MS", 5.0)
        assert v.params.get("TST_F") == -3.25 and v.params.get("IMU_MSG_MS") == 200
    # the sets persist across a runtime restart
    with SyntheticVehicle([f"udpout:127.0.0.1:{port}"], extra_params=EXTRA,
                          params_file=params_file) as v2, mavsdk_on(port) as system:
        assert v2.params.get("TST_BIG") == 2**31 - 1
        param = Param(system)
        assert param.get_param_int("TST_BIG") == 2**31 - 1
        assert param.get_param_float("TST_F") == -3.25
        assert param.get_param_int("IMU_MSG_MS") == 200
