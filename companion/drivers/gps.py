"""GPS driver thread: paced by the receiver's sentences, one solution per epoch to the GPS slot.

An epoch is handed off as soon as every expected sentence of it has arrived, or when the line
has been quiet for GPS_IDLE_MS; the measured latency (first byte of the epoch to hand-off) is
published with the solution, because the estimator must compare a GPS fix with the state at the
time the receiver computed it, not the time the driver finished reading it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

from companion.core.params import ParamSpec, int_param
from companion.core.state import GpsFix
from companion.drivers.gps_protocol import NmeaDecoder
from companion.drivers.gps_solution import GpsSolution
from companion.drivers.serial_device import SerialDevice
from companion.logs.layout import RecordLayout
from companion.watchdog.task import Task

FMT_SOLUTION = 1
FMT_RAW = 2
EXPECTED = ("GGA", "RMC", "VTG", "GSA", "GST")
UTC_JUMP_S = 1.0
"""More than any receiver latency jitter, less than a leap second's or a reset's step."""
IDLE_READ_TIMEOUT_S = 0.25
"""A read's timeout while no epoch is open: a silent receiver still returns from `step`
four times per 1000 ms watchdog window (reported as silent, never as stalled)."""


FIX_LAYOUT = RecordLayout.of(GpsFix)
"""Format 1 of gps.bin: the GpsFix record's logged fields."""


def solution_to_fix(sol: GpsSolution, t_ns: int, *, heading: bool = True) -> GpsFix:
    """The receiver's epoch as the flight uses it: the wire-level details (date, ellipsoid
    height, sentence list) stay in the decoder's GpsSolution; the horizontal error is one
    figure."""
    return GpsFix(
        t_ns=t_ns, utc_s=sol.utc, lat_deg=sol.lat_deg, lon_deg=sol.lon_deg, alt_m=sol.alt_m,
        fix=sol.fix, sats=sol.sats, hdop=sol.hdop, pdop=sol.pdop, vdop=sol.vdop, tdop=sol.tdop,
        speed_m_s=sol.speed_m_s, course_deg=sol.course_deg, vn_m_s=sol.vn_m_s,
        ve_m_s=sol.ve_m_s, vd_m_s=sol.vd_m_s, alt_std_m=sol.alt_std_m,
        h_std_m=(math.hypot(sol.lat_std_m, sol.lon_std_m)
                 if sol.lat_std_m is not None and sol.lon_std_m is not None else None),
        latency_s=sol.latency_s, heading_deg=sol.heading_deg if heading else None)


def define_fix_log(tlog: Any) -> None:
    """The format of ``gps.bin``'s fixes, whoever produces them (this driver, or an autopilot
    link whose GPS takes the slot): the record's own layout."""
    tlog.define(FMT_SOLUTION, FIX_LAYOUT.fmt, FIX_LAYOUT.names)


class GpsDriver(SerialDevice):
    """Decodes NMEA epochs; every epoch handed off is a GpsFix (a cycle) and a log record."""

    raw_format = FMT_RAW

    def __init__(self, url: str, baudrate: int = 115200, *, task: Task) -> None:
        super().__init__(task, url=url, baudrate=baudrate, read_timeout_s=0.02)
        self.decoder = self._new_decoder(allow_no_checksum=False, idle_ms=20)
        self._last_utc_s: float | None = None
        self._last_epoch: tuple[float, int] | None = None  # (receiver UTC s, arrival ns)
        self.repeated = 0
        """Epochs with the UTC of the epoch before: a receiver sending copies, not fixes."""
        self.utc_jumps = 0
        """Times the receiver's UTC moved against the computer's clock by more than
        UTC_JUMP_S between two epochs (a receiver reset, a leap second, a week rollover)."""
        self.late_epochs = 0
        """Epochs that arrived more than UTC_JUMP_S later than the receiver's clock says, after
        epochs that waited in the port's buffer (the process was suspended or starved)."""

    @staticmethod
    def _new_decoder(*, allow_no_checksum: bool, idle_ms: int, pashr: bool = False,
                     hdt: bool = False) -> NmeaDecoder:
        expected = EXPECTED + (("POS",) if pashr else ()) + (("HDT",) if hdt else ())
        return NmeaDecoder(allow_no_checksum=allow_no_checksum, expected_sentences=expected,
                           idle_handoff_ms=idle_ms)

    @classmethod
    def declare_params(cls, p: str) -> list[ParamSpec]:
        return super().declare_params(p) + [
            int_param(f"{p}_NO_CKSUM", 0, 0, 1, "",
                      "1 accepts NMEA sentences without a checksum (some old receivers)."),
            int_param(f"{p}_IDLE_MS", 20, 1, 500, "ms",
                      "Hand an epoch off after this much silence if not every expected sentence came."),
            int_param(f"{p}_PASHR", 0, 0, 1, "",
                      "1: the receiver sends Ashtech $PASHR,POS every epoch; an epoch is complete "
                      "only with it (otherwise it would arrive after the hand-off)."),
            int_param(f"{p}_HDT", 0, 0, 1, "",
                      "1: a dual-antenna receiver sends $--HDT (true heading) every epoch; an "
                      "epoch is complete only with it, so the heading travels with its own fix."),
        ]

    def define_logs(self, tlog: Any) -> None:
        define_fix_log(tlog)
        super().define_logs(tlog)

    def configure(self) -> None:
        super().configure()
        pashr = bool(self.param("PASHR"))
        hdt = bool(self.param("HDT"))
        if pashr != ("POS" in self.decoder.expected) or hdt != ("HDT" in self.decoder.expected):
            self.decoder = self._new_decoder(allow_no_checksum=bool(self.param("NO_CKSUM")),
                                             idle_ms=int(self.param("IDLE_MS")), pashr=pashr,
                                             hdt=hdt)
        self.decoder.allow_no_checksum = bool(self.param("NO_CKSUM"))
        self.decoder.idle_handoff_ns = int(self.param("IDLE_MS")) * 1_000_000

    def read_timeout_now_s(self) -> float:
        # Short reads only while an epoch waits for its idle hand-off; between epochs a read
        # waits for the next one (at 10 Hz, 4 of 5 of the short timeouts found nothing).
        return self.read_timeout_s if self.decoder.holds_epoch else IDLE_READ_TIMEOUT_S

    def drain_decoder(self, t_ns: int) -> list[object]:
        return list(self.decoder.flush(t_ns))

    def on_port_opened(self) -> None:
        self.decoder.reset()

    def recover(self) -> None:
        self.decoder = self._new_decoder(allow_no_checksum=bool(self.param("NO_CKSUM")),
                                         idle_ms=int(self.param("IDLE_MS")),
                                         pashr=bool(self.param("PASHR")),
                                         hdt=bool(self.param("HDT")))

    def decode(self, data: bytes | None, t_ns: int) -> Iterable[object]:
        solutions = self.decoder.feed(data, t_ns) if data else []
        return solutions + self.decoder.poll(t_ns)  # an epoch may end on silence

    def publish(self, item: object, t_ns: int) -> int:
        if not isinstance(item, GpsSolution):
            return 0
        if item.utc is not None:
            if item.utc == self._last_utc_s:
                self.repeated += 1
                self.notice("repeated epochs dropped (receiver sends copies)")
                return 0
            self._last_utc_s = item.utc
            self._check_utc(item.utc, t_ns)
        # a heading only when the receiver is declared to send one per epoch (GPS_HDT):
        # otherwise an HDT sent after the timed sentences joins the next epoch, 0.1 s stale
        fix = solution_to_fix(item, t_ns, heading="HDT" in self.decoder.expected)
        self.ctx.state.gps.write(fix)
        if self.tlog is not None:
            self.tlog.log(FMT_SOLUTION, *FIX_LAYOUT.values(fix), t_ns=t_ns)
        return 1

    def _check_utc(self, utc_s: float, t_ns: int) -> None:
        """Nothing on board steers by the receiver's UTC (every timestamp is the computer's
        clock), so a jump costs nothing but a confusing log: say so when it happens.

        A jump is the receiver's clock moving backwards, or forwards by more than the time
        that passed between the two epochs' arrivals. Epochs that waited in the port's buffer
        (the process was suspended) arrive later than their UTC says but one epoch apart: that
        is late data, counted as such (`late_epochs`), not a jump of the receiver's clock."""
        previous = self._last_epoch
        self._last_epoch = (utc_s, t_ns)
        if previous is None:
            return
        utc_step = (utc_s - previous[0] + 43200.0) % 86400.0 - 43200.0  # across midnight
        arrival_step = (t_ns - previous[1]) / 1e9
        if utc_step < -UTC_JUMP_S or utc_step > arrival_step + UTC_JUMP_S:
            self.utc_jumps += 1
            self.notice(f"receiver UTC jumped {utc_step - arrival_step:+.1f} s against the clock",
                        key="utc")
        elif utc_step < arrival_step - UTC_JUMP_S:
            self.late_epochs += 1
            self.notice(f"epochs arrived {arrival_step - utc_step:.1f} s late (buffered)",
                        key="late")

    def counters(self) -> dict[str, int]:
        out = super().counters()
        out.update(repeated=self.repeated, utc_jumps=self.utc_jumps, late_epochs=self.late_epochs)
        c = self.decoder.counters
        out.update({k: getattr(c, k) for k in (
            "sentences_good", "bad_checksum", "unknown", "too_long", "cut", "malformed", "late",
            "bytes_discarded", "epochs")})
        return out
