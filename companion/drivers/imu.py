"""IMU driver thread: paced by the IMU's 100 Hz frames, publishes SI samples to the IMU slot."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from companion.core.state import ImuSample, ImuSlowSample
from companion.drivers.imu_protocol import ImuDecoder, ImuFast, ImuSlow
from companion.drivers.serial_device import SerialDevice
from companion.watchdog.task import Task

FMT_FAST = 1
FMT_SLOW = 2
FMT_RAW = 3


def define_sample_logs(tlog: Any) -> None:
    """The formats of ``imu.bin``'s samples, whoever produces them (this driver, or an
    autopilot link whose IMU takes the slot): the report and the converters read one layout."""
    tlog.define(FMT_FAST, "%hhu,%hhu,%.6f,%.6f,%.6f,%.5f,%.5f,%.5f",
                ["counter", "status", "p_rad_s", "q_rad_s", "r_rad_s",
                 "ax_m_s2", "ay_m_s2", "az_m_s2"])
    tlog.define(FMT_SLOW, "%.7f,%.7f,%.7f,%.6f,%.6f,%.6f,%.2f,%hu",
                ["p_rad_s", "q_rad_s", "r_rad_s", "ax_m_s2", "ay_m_s2", "az_m_s2",
                 "temperature_c", "bit_word"])


class ImuDriver(SerialDevice):
    """Decodes the IMU's frames; a fast frame is a sample (a cycle), a slow block is not."""

    raw_format = FMT_RAW

    def __init__(self, url: str, baudrate: int = 115200, *, task: Task) -> None:
        super().__init__(task, url=url, baudrate=baudrate)
        self.decoder = ImuDecoder()
        self._last_fast: tuple[object, ...] | None = None
        self.repeated = 0
        """Fast frames identical to the one before (counter and every field): a device that
        sends copies, not samples. Each would be a second sample at the same instant."""

    def define_logs(self, tlog: Any) -> None:
        define_sample_logs(tlog)
        super().define_logs(tlog)

    def on_port_opened(self) -> None:
        self.decoder.reset()
        self._last_fast = None

    def recover(self) -> None:
        self.decoder.reset()
        self._last_fast = None

    def decode(self, data: bytes | None, t_ns: int) -> Iterable[object]:
        return self.decoder.feed(data, t_ns) if data else ()

    def publish(self, item: object, t_ns: int) -> int:
        state = self.ctx.state
        tlog = self.tlog
        if isinstance(item, ImuFast):
            key = (item.counter, item.status, item.rates_rad_s, item.accel_m_s2, item.slow_word)
            if key == self._last_fast:
                self.repeated += 1
                self.notice("repeated frames dropped (device sends copies)")
                return 0
            self._last_fast = key
            sample = ImuSample(t_ns, item.counter, item.rates_rad_s, item.accel_m_s2,
                               item.gyro_ok, item.accel_ok)
            state.imu.write(sample)
            state.imu_stream.put(sample)
            if tlog is not None:
                tlog.log(FMT_FAST, item.counter, item.status, *item.rates_rad_s,
                         *item.accel_m_s2, t_ns=t_ns)
            return 1
        if isinstance(item, ImuSlow):
            state.imu_slow.write(ImuSlowSample(t_ns, item.rates_rad_s, item.accel_m_s2,
                                               item.temperature_c, item.bit_word))
            if tlog is not None:
                tlog.log(FMT_SLOW, *item.rates_rad_s, *item.accel_m_s2, item.temperature_c,
                         item.bit_word, t_ns=t_ns)
        return 0

    def counters(self) -> dict[str, int]:
        out = super().counters()
        out.update({k: getattr(self.decoder.counters, k) for k in
                    ("frames_good", "bad_checksum", "bad_field", "resyncs", "bytes_discarded",
                     "slow_good", "slow_dropped")})
        out["repeated"] = self.repeated
        return out
