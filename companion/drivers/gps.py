"""GPS driver thread: paced by the receiver's sentences, one solution per epoch to the GPS slot.

An epoch is handed off as soon as every expected sentence of it has arrived, or when the line
has been quiet for GPS_IDLE_MS; the measured latency (first byte of the epoch to hand-off) is
published with the solution, because the estimator must compare a GPS fix with the state at the
time the receiver computed it, not the time the driver finished reading it.
"""

from __future__ import annotations

import math
from typing import Any

from companion.core.params import ParamSpec, int_param
from companion.core.state import GpsFix
from companion.drivers.gps_protocol import GpsSolution, NmeaDecoder
from companion.drivers.serial_device import SerialDevice

FMT_SOLUTION = 1
FMT_RAW = 2
EXPECTED = ("GGA", "RMC", "VTG", "GSA", "GST")


def _nan(value: float | None) -> float:
    return math.nan if value is None else float(value)


def solution_to_fix(sol: GpsSolution, t_ns: int) -> GpsFix:
    return GpsFix(
        t_ns=t_ns, utc_s=sol.utc, lat_deg=sol.lat_deg, lon_deg=sol.lon_deg, alt_m=sol.alt_m,
        fix=sol.fix, sats=sol.sats, hdop=sol.hdop, pdop=sol.pdop, vdop=sol.vdop, tdop=sol.tdop,
        speed_m_s=sol.speed_m_s, course_deg=sol.course_deg, vn_m_s=sol.vn_m_s,
        ve_m_s=sol.ve_m_s, vd_m_s=sol.vd_m_s, alt_std_m=sol.alt_std_m,
        h_std_m=(math.hypot(sol.lat_std_m, sol.lon_std_m)
                 if sol.lat_std_m is not None and sol.lon_std_m is not None else None),
        latency_s=sol.latency_s)


class GpsDriver(SerialDevice):
    def __init__(self, url: str, baudrate: int = 115200, *, name: str = "gps", thread_id: int = 2) -> None:
        super().__init__(name, thread_id=thread_id, url=url, baudrate=baudrate,
                         watchdog_ms=1000, message_ms=1000, budget_ms=5.0, read_timeout_s=0.02)
        self.decoder = self._new_decoder(allow_no_checksum=False, idle_ms=20)

    @staticmethod
    def _new_decoder(*, allow_no_checksum: bool, idle_ms: int, pashr: bool = False) -> NmeaDecoder:
        expected = EXPECTED + (("POS",) if pashr else ())
        return NmeaDecoder(allow_no_checksum=allow_no_checksum, expected_sentences=expected,
                           idle_handoff_ms=idle_ms)

    def declare_params(self) -> list[ParamSpec]:
        p = self.param_prefix
        return [
            int_param(f"{p}_NO_CKSUM", 0, 0, 1, "",
                      "1 accepts NMEA sentences without a checksum (some old receivers)."),
            int_param(f"{p}_IDLE_MS", 20, 1, 500, "ms",
                      "Hand an epoch off after this much silence if not every expected sentence came."),
            int_param(f"{p}_LOG_RAW", 1, 0, 1, "", "1 logs the receiver's raw bytes too."),
            int_param(f"{p}_PASHR", 0, 0, 1, "",
                      "1: the receiver sends Ashtech $PASHR,POS every epoch; an epoch is complete "
                      "only with it (otherwise it would arrive after the hand-off)."),
        ]

    def define_logs(self, tlog: Any) -> None:
        tlog.define(FMT_SOLUTION,
                    "%.3f,%.9lf,%.9lf,%.3f,%hhu,%hhu,%.2f,%.2f,%.2f,%.2f,%.3f,%.2f,%.3f,%.3f,%.3f,"
                    "%.3f,%.3f,%.2f",
                    ["utc_s", "lat_deg", "lon_deg", "alt_m", "fix", "sats", "hdop", "pdop", "vdop",
                     "tdop", "speed_m_s", "course_deg", "vn_m_s", "ve_m_s", "vd_m_s", "alt_std_m",
                     "h_std_m", "latency_ms"])
        tlog.define(FMT_RAW, "%02hhX", ["raw_bytes"])

    def _configure(self) -> None:
        pashr = bool(self.param("PASHR"))
        if pashr != ("POS" in self.decoder.expected):
            self.decoder = self._new_decoder(allow_no_checksum=bool(self.param("NO_CKSUM")),
                                             idle_ms=int(self.param("IDLE_MS")), pashr=pashr)
        self.decoder.allow_no_checksum = bool(self.param("NO_CKSUM"))
        self.decoder.idle_handoff_ns = int(self.param("IDLE_MS")) * 1_000_000
        self.log_raw = bool(self.param("LOG_RAW"))

    def prologue(self) -> bool:
        self._configure()
        return True

    def drain_decoder(self, t_ns: int) -> list[object]:
        return list(self.decoder.flush(t_ns))

    def on_params_changed(self) -> None:
        self._configure()

    def on_port_opened(self) -> None:
        self.decoder.reset()

    def recover(self) -> None:
        self.decoder = self._new_decoder(allow_no_checksum=bool(self.param("NO_CKSUM")),
                                         idle_ms=int(self.param("IDLE_MS")),
                                         pashr=bool(self.param("PASHR")))

    def step(self) -> int:
        data = self.read_chunk()
        clock = self.ctx.clock
        t_ns = clock.realtime_ns()
        solutions: list[GpsSolution] = []
        if data:
            if self.tlog is not None and self.log_raw:
                self.tlog.log_array(FMT_RAW, data, t_ns=t_ns)
            solutions = self.decoder.feed(data, t_ns)
        solutions += self.decoder.poll(t_ns)
        sink = self.item_sink
        for sol in solutions:
            if sink is not None:
                sink(sol)
            fix = solution_to_fix(sol, t_ns)
            self.ctx.state.gps.write(fix)
            if self.tlog is not None:
                self.tlog.log(
                    FMT_SOLUTION, _nan(sol.utc), _nan(sol.lat_deg), _nan(sol.lon_deg),
                    _nan(sol.alt_m), sol.fix, sol.sats or 0, _nan(sol.hdop), _nan(sol.pdop),
                    _nan(sol.vdop), _nan(sol.tdop), _nan(sol.speed_m_s), _nan(sol.course_deg),
                    _nan(sol.vn_m_s), _nan(sol.ve_m_s), _nan(sol.vd_m_s), _nan(sol.alt_std_m),
                    _nan(fix.h_std_m),
                    _nan(None if sol.latency_s is None else sol.latency_s * 1e3), t_ns=t_ns)
        return len(solutions)

    def counters(self) -> dict[str, int]:
        out = super().counters()
        c = self.decoder.counters
        out.update({k: getattr(c, k) for k in (
            "sentences_good", "bad_checksum", "unknown", "too_long", "cut", "malformed", "late",
            "bytes_discarded", "epochs")})
        return out
