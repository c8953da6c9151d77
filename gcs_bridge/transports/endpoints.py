"""Endpoint strings: pymavlink connection strings plus optional per-link settings.

An endpoint is what `--mavlink` and `[mavlink] endpoints` take: a pymavlink connection string
(`udpout:127.0.0.1:14550`, `udpin:0.0.0.0:14550`, `tcpin:0.0.0.0:5760`, `tcp:host:port`,
`/dev/ttyUSB0,57600`, or a pyserial URL such as `loop://`), optionally followed by
`?key=value&key=value` settings for that link only:

- `signing=on|off`: with a key file, `off` exempts this link (a wired link on the bench);
- `unsigned_reads=1|0`: with a key, accept unsigned messages that change nothing;
- `identity=generic|px4|ardupilot`: the autopilot this link's HEARTBEAT claims (default
  generic), which fixes how its clients encode integer parameters (MAVProxy needs `px4`);
- `MESSAGE_NAME=hz`: start this link with that message at that rate (0 = off), e.g.
  `ATTITUDE=10&GPS_RAW_INT=2`, so a slow radio and a fast wired link can differ.

`autopilot:` is no connection of its own: the companion's component is served over the
autopilot link's connection (`--autopilot URL`), for a companion that is one endpoint of the
user's MAVLink router (mavlink-router, BlueOS; see docs/ground-stations.md).

Settings after `?` never reach pymavlink, which has no such syntax; `?` appears in no pymavlink
connection string, so the split is unambiguous.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

from companion.core.config import ConfigError
from gcs_bridge.dialect import Identity, message_id

DEFAULT_ENDPOINT = "udpout:127.0.0.1:14550"
DEFAULT_SERIAL_BAUD = 57600

_TRUE = {"1", "on", "yes", "true"}
_FALSE = {"0", "off", "no", "false"}


class EndpointError(ConfigError):
    """An endpoint string that cannot be used; the message names the endpoint and the part.

    A ConfigError, so the `companion` command reports it as a configuration error.
    """

    def __init__(self, endpoint: str, problem: str) -> None:
        super().__init__(f"MAVLink endpoint {endpoint!r}: {problem}")
        self.endpoint = endpoint
        self.problem = problem


@dataclass(frozen=True)
class Endpoint:
    """One parsed endpoint: where to connect and how this link behaves."""

    text: str  # as given, for messages
    kind: str  # udpin | udpout | udpbcast | tcpin | tcp | serial | autopilot
    host: str = ""
    port: int = 0
    device: str = ""  # serial device path or pyserial URL
    baud: int = DEFAULT_SERIAL_BAUD
    signing: bool | None = None  # None: on when the bridge has a key
    unsigned_reads: bool | None = None  # None: the bridge-wide default
    identity: Identity = Identity.GENERIC
    rates_hz: dict[int, float] = field(default_factory=dict)  # message id -> Hz (0 = off)

    @property
    def url(self) -> str:
        """The connection string without settings."""
        return self.text.split("?", 1)[0]

    @property
    def is_serial(self) -> bool:
        return self.kind == "serial"


def _host_port(endpoint: str, rest: str) -> tuple[str, int]:
    host, sep, port_text = rest.rpartition(":")
    if not sep or not host:
        raise EndpointError(endpoint, f"expected HOST:PORT after the scheme, got {rest!r}")
    try:
        port = int(port_text)
    except ValueError:
        raise EndpointError(endpoint, f"port {port_text!r} is not a number") from None
    if not 0 <= port <= 65535:
        raise EndpointError(endpoint, f"port {port} outside 0..65535")
    return host, port


def _flag(endpoint: str, key: str, value: str) -> bool:
    v = value.strip().lower()
    if v in _TRUE:
        return True
    if v in _FALSE:
        return False
    raise EndpointError(endpoint, f"setting {key}={value!r}: expected on/off or 1/0")


def parse_endpoint(text: str) -> Endpoint:
    """Parse one endpoint string; raises EndpointError saying what is wrong and where."""
    if not isinstance(text, str) or not text.strip():
        raise EndpointError(str(text), "empty endpoint")
    text = text.strip()
    url, _, query = text.partition("?")
    settings: dict[str, object] = {}
    rates: dict[int, float] = {}
    if query:
        for item in query.split("&"):
            if not item:
                continue
            key, eq, value = item.partition("=")
            if not eq:
                raise EndpointError(text, f"setting {item!r} must be KEY=VALUE")
            lkey = key.strip().lower()
            if lkey == "signing":
                settings["signing"] = _flag(text, key, value)
            elif lkey == "unsigned_reads":
                settings["unsigned_reads"] = _flag(text, key, value)
            elif lkey == "identity":
                try:
                    settings["identity"] = Identity.parse(value)
                except ValueError as exc:
                    raise EndpointError(text, f"setting {exc}") from None
            else:
                msg_id = message_id(key.strip())
                if msg_id is None:
                    raise EndpointError(
                        text, f"unknown setting {key!r} (signing, unsigned_reads, identity or a MAVLink "
                              "message name such as ATTITUDE)")
                try:
                    hz = float(value)
                except ValueError:
                    raise EndpointError(text, f"rate {key}={value!r} is not a number") from None
                if not math.isfinite(hz) or hz < 0 or hz > 1000:
                    raise EndpointError(text, f"rate {key}={value!r} outside 0..1000 Hz")
                rates[msg_id] = hz
    scheme, colon, rest = url.partition(":")
    common: dict[str, object] = dict(settings)
    common["rates_hz"] = rates
    if colon and scheme in ("udpin", "udpout", "udpbcast", "udp", "tcpin", "tcp"):
        host, port = _host_port(text, rest)
        kind = "udpin" if scheme == "udp" else scheme
        if kind in ("udpout", "udpbcast", "tcp") and port == 0:
            raise EndpointError(text, "a destination port cannot be 0")
        return Endpoint(text=text, kind=kind, host=host, port=port, **common)  # type: ignore[arg-type]
    if url in ("autopilot", "autopilot:"):  # the autopilot link's connection, shared
        return Endpoint(text=text, kind="autopilot", **common)  # type: ignore[arg-type]
    if "://" in url:  # a pyserial URL (loop://, socket://, rfc2217://, spy://)
        return Endpoint(text=text, kind="serial", device=url, **common)  # type: ignore[arg-type]
    device, comma, baud_text = url.partition(",")
    if comma or device.startswith("/") or os.path.exists(device):
        baud = DEFAULT_SERIAL_BAUD
        if comma:
            try:
                baud = int(baud_text)
            except ValueError:
                raise EndpointError(text, f"baud rate {baud_text!r} is not a number") from None
            if baud <= 0:
                raise EndpointError(text, f"baud rate {baud} must be positive")
        return Endpoint(text=text, kind="serial", device=device, baud=baud, **common)  # type: ignore[arg-type]
    if ":" in url:  # pymavlink reads a bare HOST:PORT as a UDP input
        host, port = _host_port(text, url)
        return Endpoint(text=text, kind="udpin", host=host, port=port, **common)  # type: ignore[arg-type]
    raise EndpointError(
        text, "not a connection string: use udpin:/udpout:/tcpin:/tcp:HOST:PORT, a serial "
              "device such as /dev/ttyUSB0,57600, or a pyserial URL")
