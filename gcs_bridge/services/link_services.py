"""The bridge's services beyond telemetry and parameters: flights (LOG_*), files (MAVLink FTP),
component metadata and the console, wired to one link.

Each link gets its own `LinkServices`: its own log snapshot, FTP sessions and console line, so
one ground station's download or typing never disturbs another's. Requests arrive in the link's
receive thread and are handed to its send thread as paced transfers (`gcs_bridge.bulk`), so
disk reads and long answers happen where telemetry is sent and never ahead of it.

Hostile or broken ground stations: every answer to a LOG_* or FTP request goes through the
link's bulk sender, so it is paced by MAV_BULK_KB_S whatever the request rate; a log data
request replaces the one before, FTP requests queue up to `bulk.MAX_PENDING`. The only answer
that is not a transfer, the STATUSTEXT about an unknown log id, is sent at most once per
`UNKNOWN_LOG_REPORT_S` (the others are counted in `unknown_log_requests`): before, a storm of
such requests was reflected one STATUSTEXT each, five times the bulk budget.

Who may do what: listing and downloading are reads. Erasing flights, the console and FTP writes
change the aircraft: on a link with signing they need a signed message (the signing policy
refuses unsigned LOG_ERASE and SERIAL_CONTROL before they get here; FTP writes additionally
need a key to be set at all, see `may_write_files`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Protocol

from gcs_bridge import status
from gcs_bridge.bulk import BulkSender
from gcs_bridge.dialect import Identity, RxMessage, mavlink
from gcs_bridge.dialect import Message as Msg
from gcs_bridge.runtime_view import BridgeCore
from gcs_bridge.services.console import Console
from gcs_bridge.services.ftp import FtpServer
from gcs_bridge.services.ftp_wire import PAYLOAD_LEN
from gcs_bridge.services.log_download import LogServer, first_log_id
from gcs_bridge.services.metadata import ComponentMetadata
from gcs_bridge.signing import LinkPolicy

log = logging.getLogger(__name__)

LOG_CHANNEL = "log"
FTP_CHANNEL = "ftp"
CONSOLE_CHANNEL = "console"
NO_FLIGHTS = Path("/nonexistent-flight-root")  # FTP then serves only the metadata files
UNKNOWN_LOG_REPORT_S = 1.0  # at most one "no such log" STATUSTEXT per link per this


class ServiceLink(Protocol):
    """The link a service answers on, as the services need it (`gcs_bridge.link.Link` is one).

    A service never sends from the receive thread: it posts a list of messages, or a function
    that the link's send thread calls with the link (there `bulk` and `emit` may be used).
    """

    index: int
    core: BridgeCore
    policy: LinkPolicy
    signed_in: bool
    text_ids: status.StatusTextIds
    bulk: BulkSender

    @property
    def identity(self) -> Identity: ...

    def post(self, item: list[Msg] | Callable[[ServiceLink], None]) -> bool: ...

    def notify(self, severity: int, text: str) -> None: ...

    def peer_alive(self, src: tuple[int, int]) -> bool: ...

    def emit(self, msgs: list[Msg]) -> None: ...


class LinkServices:
    """Per-link LOG_* service (and the other file-like services, see the module docstring)."""

    def __init__(self, link: ServiceLink, flight_root: Path | None,
                 current_flight: Callable[[], Path | None],
                 metadata: ComponentMetadata) -> None:
        self.link = link
        self.flight_root = flight_root
        self.current_flight = current_flight
        self.metadata = metadata
        self.logs = (LogServer(flight_root, current_flight,
                               first_id=first_log_id(link.identity))
                     if flight_root is not None else None)
        self.console = Console(link.core, flights=self._flights)
        self.ftp = FtpServer(flight_root if flight_root is not None else NO_FLIGHTS,
                             virtual=metadata.virtual_files(), protected=current_flight)
        self.unknown_log_requests = 0  # LOG_REQUEST_DATA for ids not in the list
        self._unknown_log_reported_s = -UNKNOWN_LOG_REPORT_S

    def close(self) -> None:
        self.ftp.close()

    @property
    def may_write_files(self) -> bool:
        """FTP may write only on a link with a key, for a message signed with it."""
        return self.link.policy.key is not None and self.link.signed_in

    # ------------------------------------------------------------------ FTP
    def ftp_request(self, msg: RxMessage) -> None:
        payload = bytes(msg.payload)
        may_write = self.may_write_files
        requester = (msg.get_srcSystem(), msg.get_srcComponent())
        ftp = self.ftp

        def start(link: ServiceLink) -> None:
            link.bulk.queue(FTP_CHANNEL, _ftp_messages(ftp.handle(payload, may_write=may_write),
                                                       requester),
                            lambda: link.peer_alive(requester))
        self.link.post(start)

    def _flights(self) -> list[tuple[str, int]]:
        """(name, bytes) of every flight, for the console's `logs`."""
        if self.logs is None:
            return []
        out = []
        for flight in self.logs.flight_dirs():
            try:
                size = sum(p.stat().st_size for p in flight.rglob("*") if p.is_file())
            except OSError:
                size = 0
            out.append((flight.name, size))
        return out

    # ------------------------------------------------------------------ console
    def serial_control(self, msg: RxMessage) -> None:
        """SERIAL_CONTROL to the shell device: the console (it can restart threads and set
        parameters, so the signing policy treats it as a write)."""
        replies = self.console.handle(msg)
        if replies:  # up to 32 KiB: paced like a download, every command's output in order
            self.link.post(lambda link: link.bulk.queue(CONSOLE_CHANNEL, iter(replies),
                                                        preempt=False))

    # ------------------------------------------------------------------ metadata
    def metadata_message(self) -> Msg:
        return self.metadata.message(self.link.core.time_boot_ms())

    # ------------------------------------------------------------------ LOG_*
    def log_request_list(self, msg: RxMessage) -> None:
        requester = (msg.get_srcSystem(), msg.get_srcComponent())
        if self.logs is None:  # no flight directory: "no logs", as the protocol says
            # through the bulk sender like any answer to a request, so a storm is paced
            self.link.post(lambda link: link.bulk.replace(
                LOG_CHANNEL, iter([mavlink.MAVLink_log_entry_message(0, 0, 0, 0, 0)])))
            return
        logs = self.logs
        start, end = int(msg.start), int(msg.end)
        self.link.post(lambda link: link.bulk.replace(
            LOG_CHANNEL, _lazy(lambda: logs.request_list(start, end)),
            lambda: link.peer_alive(requester)))

    def log_request_data(self, msg: RxMessage) -> None:
        if self.logs is None:
            return
        requester = (msg.get_srcSystem(), msg.get_srcComponent())
        logs = self.logs
        log_id, offset, count = int(msg.id), int(msg.ofs), int(msg.count)
        if logs.archive(log_id) is None:
            self.unknown_log_requests += 1
            now_s = time.monotonic()
            if now_s - self._unknown_log_reported_s >= UNKNOWN_LOG_REPORT_S:
                self._unknown_log_reported_s = now_s
                self.link.notify(mavlink.MAV_SEVERITY_WARNING, f"log {log_id}: no such log")
            return
        self.link.post(lambda link: link.bulk.replace(
            LOG_CHANNEL, _lazy(lambda: logs.request_data(log_id, offset, count)),
            lambda: link.peer_alive(requester)))

    def log_request_end(self, _msg: RxMessage) -> None:
        self.link.post(lambda link: link.bulk.cancel(LOG_CHANNEL))

    def log_erase(self, _msg: RxMessage) -> None:
        if self.logs is None:
            return
        logs = self.logs

        def erase(link: ServiceLink) -> None:
            link.bulk.cancel(LOG_CHANNEL)
            try:
                erased, text = logs.erase()
            except OSError as exc:
                log.error("link %d: erasing flights failed: %s", link.index, exc)
                link.emit(status.statustext(mavlink.MAV_SEVERITY_ERROR,
                                            f"log erase failed: {exc.strerror or exc}",
                                            link.text_ids))
                return
            log.info("link %d: %s", link.index, text)
            link.emit(status.statustext(mavlink.MAV_SEVERITY_NOTICE if erased else
                                        mavlink.MAV_SEVERITY_INFO, text, link.text_ids))
        self.link.post(erase)


def _ftp_messages(replies: Iterator[bytes | None], to: tuple[int, int]) -> Iterator[Msg | None]:
    """FILE_TRANSFER_PROTOCOL messages addressed to the client, from the server's payloads."""
    try:
        for payload in replies:
            if payload is None:
                yield None
                continue
            yield mavlink.MAVLink_file_transfer_protocol_message(
                0, to[0], to[1], list(payload.ljust(PAYLOAD_LEN, b"\0")[:PAYLOAD_LEN]))
    finally:
        close = getattr(replies, "close", None)
        if close is not None:
            close()


def _lazy(make: Callable[[], Iterator[Msg | None]]) -> Iterator[Msg | None]:
    """Create the transfer in the send thread, at its first step (disk work stays there)."""
    yield from make()
