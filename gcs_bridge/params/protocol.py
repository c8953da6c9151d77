"""The MAVLink parameter protocol over the runtime's parameter registry.

The registry's declaration order is the MAVLink index. A change, whoever makes it (a ground
station, the legacy monitor, a thread), is announced to every link with PARAM_VALUE, as the
protocol asks; a PARAM_SET that changes nothing is answered on its own link. A refused set is
answered with the unchanged value, a STATUSTEXT saying why and a PARAM_ERROR.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from companion.core.params import ParamError, ParamErrorKind, ParamSpec
from gcs_bridge.dialect import mavlink
from gcs_bridge.params import codec as param_codec
from gcs_bridge.runtime_view import BridgeCore

log = logging.getLogger(__name__)

# MAV_PARAM_ERROR values newer than pymavlink 2.4.50's common.xml (MAVSDK maps them).
PARAM_ERROR_TYPE_UNSUPPORTED = 6
PARAM_ERROR_TYPE_MISMATCH = 7


@dataclass(frozen=True)
class SetOutcome:
    """What a PARAM_SET did: `index` None when the name is unknown."""

    name: str
    index: int | None
    ok: bool
    changed: bool = False
    reason: str = ""
    error: int = 0  # MAV_PARAM_ERROR when refused


class ParamProtocol:
    """Stateless helpers over the registry; safe from any thread."""

    def __init__(self, core: BridgeCore) -> None:
        self.core = core
        self.registry = core.ctx.params

    def count(self) -> int:
        return len(self.registry)

    def value_message(self, index: int, *, bytewise: bool) -> param_codec.ParamValueMessage | None:
        """PARAM_VALUE with the current value of parameter `index`, None if out of range.

        `bytewise` is the link's integer encoding (its identity's).
        """
        try:
            name = self.registry.name_at(index)
            spec = self.registry.spec(name)
            value = self.registry.get(name)
        except ParamError:
            return None
        return param_codec.param_value_message(spec, value, index, self.count(),
                                               bytewise=bytewise)

    def index_of(self, name: str) -> int | None:
        try:
            return self.registry.index_of(name)
        except ParamError:
            return None

    def lookup(self, param_id: str, param_index: int) -> int | None:
        """PARAM_REQUEST_READ: by name when the index is -1, else by index."""
        if param_index == -1:
            return self.index_of(param_id)
        return param_index if 0 <= param_index < self.count() else None

    def apply_set(self, param_id: str, raw: bytes, mav_type: int, *,
                  bytewise: bool) -> SetOutcome:
        """Validate and apply a PARAM_SET given its raw value bytes."""
        name = param_id.strip("\0").strip()
        index = self.index_of(name)
        if index is None:
            return SetOutcome(name, None, False, reason="unknown parameter",
                              error=mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST)
        spec = self.registry.spec(name)
        if spec.read_only:
            return SetOutcome(name, index, False, reason="read-only",
                              error=mavlink.MAV_PARAM_ERROR_READ_ONLY)
        if not param_codec.type_matches(spec, mav_type):
            return SetOutcome(
                name, index, False,
                reason=f"wrong type: {param_codec.type_name(mav_type)} for a "
                       f"{spec.ptype.value} parameter",
                error=PARAM_ERROR_TYPE_MISMATCH)
        try:
            value = param_codec.decode(raw, mav_type, bytewise=bytewise)
        except param_codec.WireValueError as exc:
            code = (PARAM_ERROR_TYPE_UNSUPPORTED if "not supported" in exc.reason
                    else PARAM_ERROR_TYPE_MISMATCH)
            return SetOutcome(name, index, False, reason=exc.reason, error=code)
        before = self.registry.get(name)
        try:
            after = self.registry.set(name, value)  # every rule between parameters applies here
        except ParamError as exc:
            return SetOutcome(name, index, False, reason=exc.reason, error=_ERROR_CODES[exc.kind])
        log.info("parameter %s set to %s from MAVLink", name, after)
        return SetOutcome(name, index, True, changed=(after != before),
                          reason="takes effect at the next start" if spec.reboot_required else "")

    def spec(self, name: str) -> ParamSpec:
        return self.registry.spec(name)


_ERROR_CODES = {
    ParamErrorKind.UNKNOWN: int(mavlink.MAV_PARAM_ERROR_DOES_NOT_EXIST),
    ParamErrorKind.READ_ONLY: int(mavlink.MAV_PARAM_ERROR_READ_ONLY),
    ParamErrorKind.WRONG_TYPE: PARAM_ERROR_TYPE_MISMATCH,
    ParamErrorKind.OUT_OF_RANGE: int(mavlink.MAV_PARAM_ERROR_VALUE_OUT_OF_RANGE),
    ParamErrorKind.CONFLICT: int(mavlink.MAV_PARAM_ERROR_VALUE_OUT_OF_RANGE),
}
"""The registry's refusal kinds in MAVLink's PARAM_ERROR terms (a conflict with another
parameter has no code of its own; the reason text goes out in the STATUSTEXT)."""
