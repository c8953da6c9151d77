"""Garbage never becomes a legal parameter value (PARAM_SET on MAVLink, SET_* in the legacy
protocol): every parameter the runtime declares, every wire type, both integer conventions,
any four bytes. What is accepted is a value of the declared type, sent in that type's one form;
everything else is refused with a reason naming what was wrong.
"""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from companion.core.config import Config
from companion.core.params import ParamRegistry, ParamType
from companion.runtime import declared_registry
from companion.vehicle import VEHICLE, fill_device_defaults
from gcs_bridge.params import codec
from gcs_bridge.params.protocol import ParamProtocol

TYPES = [codec.T_UINT8, codec.T_INT8, codec.T_UINT16, codec.T_INT16, codec.T_UINT32,
         codec.T_INT32, codec.T_REAL32]
_FMT = {codec.T_UINT8: "<B", codec.T_INT8: "<b", codec.T_UINT16: "<H", codec.T_INT16: "<h",
        codec.T_UINT32: "<I", codec.T_INT32: "<i"}


def _registry() -> ParamRegistry:
    cfg = fill_device_defaults(Config(), VEHICLE)
    for settings_ in cfg.devices.values():
        settings_.enabled = True
    return declared_registry(cfg)


REGISTRY = _registry()
NAMES = sorted(spec.name for spec in REGISTRY.specs() if not spec.read_only)


class _Protocol(ParamProtocol):
    """The bridge's parameter protocol on a registry of its own (no links are needed to set)."""

    def __init__(self, registry: ParamRegistry) -> None:  # noqa: D107 - no core: no links
        self.registry = registry


def _canonical(raw: bytes, mav_type: int, bytewise: bool, value: float) -> bool:
    """Whether `raw` is `value` written the one way a ground station writes it in `mav_type`."""
    if mav_type == codec.T_REAL32:
        return math.isfinite(struct.unpack("<f", raw)[0])
    if not bytewise:
        f = struct.unpack("<f", raw)[0]
        return math.isfinite(f) and f == int(f) and int(f) == value
    fmt = _FMT[mav_type]
    size = struct.calcsize(fmt)
    head = struct.pack(fmt, int(value))
    pads = (b"\x00", b"\xff") if value < 0 else (b"\x00",)
    return any(raw == head + pad * (4 - size) for pad in pads)


@settings(max_examples=3000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(name=st.sampled_from(NAMES), mav_type=st.sampled_from(TYPES), bytewise=st.booleans(),
       raw=st.one_of(
           st.binary(min_size=4, max_size=4),
           st.sampled_from([struct.pack("<f", v) for v in (math.nan, math.inf, -math.inf, 1e30,
                                                           -1e30, 2.0 ** 31, -(2.0 ** 31),
                                                           0.5, -0.0)]),
           st.integers(-(2 ** 31), 2 ** 31 - 1).map(lambda i: struct.pack("<i", i))))
def test_no_garbage_value_is_ever_accepted(name: str, mav_type: int, bytewise: bool,
                                           raw: bytes) -> None:
    registry = ParamRegistry()
    registry.declare_all(REGISTRY.specs())
    spec = registry.spec(name)
    before = registry.get(name)
    outcome = _Protocol(registry).apply_set(name, raw, mav_type, bytewise=bytewise)
    after = registry.get(name)
    if not outcome.ok:
        assert after == before and outcome.reason
        return
    assert math.isfinite(after) and spec.min <= after <= spec.max
    if spec.ptype is ParamType.INT32:
        assert isinstance(after, int)
    assert _canonical(raw, mav_type, bytewise, after), (name, raw.hex(), mav_type, after)


@pytest.mark.parametrize("raw,mav_type,bytewise,why", [
    (struct.pack("<f", math.nan), codec.T_UINT8, True, "are not a uint8"),
    (struct.pack("<f", 1e30), codec.T_INT16, True, "are not a int16"),
    (struct.pack("<f", math.nan), codec.T_REAL32, True, "not a finite number"),
    (struct.pack("<f", math.inf), codec.T_INT32, False, "not an integer"),
    (struct.pack("<f", 300.0), codec.T_UINT8, False, "does not fit a uint8"),
])
def test_what_a_refusal_says(raw: bytes, mav_type: int, bytewise: bool, why: str) -> None:
    registry = ParamRegistry()
    registry.declare_all(REGISTRY.specs())
    outcome = _Protocol(registry).apply_set("CTL_MODE", raw, mav_type, bytewise=bytewise)
    assert not outcome.ok and why in outcome.reason
