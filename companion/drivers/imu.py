"""IMU driver thread: paced by the IMU's 100 Hz frames, publishes SI samples to the IMU slot."""

from __future__ import annotations

from typing import Any

from companion.core.params import ParamSpec, int_param
from companion.core.state import ImuSample, ImuSlowSample
from companion.drivers.imu_protocol import ImuDecoder, ImuFast, ImuSlow
from companion.drivers.serial_device import SerialDevice

FMT_FAST = 1
FMT_SLOW = 2
FMT_RAW = 3


class ImuDriver(SerialDevice):
    def __init__(self, url: str, baudrate: int = 115200, *, name: str = "imu", thread_id: int = 1) -> None:
        super().__init__(name, thread_id=thread_id, url=url, baudrate=baudrate,
                         watchdog_ms=500, message_ms=1000, budget_ms=2.0)
        self.decoder = ImuDecoder()
        self.log_raw = True

    def declare_params(self) -> list[ParamSpec]:
        return [int_param(f"{self.param_prefix}_LOG_RAW", 1, 0, 1, "",
                          "1 logs the IMU's raw bytes too (a replayable capture)."),]

    def define_logs(self, tlog: Any) -> None:
        tlog.define(FMT_FAST, "%hhu,%hhu,%.6f,%.6f,%.6f,%.5f,%.5f,%.5f",
                    ["counter", "status", "p_rad_s", "q_rad_s", "r_rad_s",
                     "ax_m_s2", "ay_m_s2", "az_m_s2"])
        tlog.define(FMT_SLOW, "%.7f,%.7f,%.7f,%.6f,%.6f,%.6f,%.2f,%hu",
                    ["p_rad_s", "q_rad_s", "r_rad_s", "ax_m_s2", "ay_m_s2", "az_m_s2",
                     "temperature_c", "bit_word"])
        tlog.define(FMT_RAW, "%02hhX", ["raw_bytes"])

    def on_params_changed(self) -> None:
        self.log_raw = bool(self.param("LOG_RAW"))

    def prologue(self) -> bool:
        self.log_raw = bool(self.param("LOG_RAW"))
        return True

    def on_port_opened(self) -> None:
        self.decoder.reset()

    def recover(self) -> None:
        self.decoder.reset()

    def step(self) -> int:
        data = self.read_chunk()
        if not data:
            return False
        t_ns = self.ctx.clock.realtime_ns()
        tlog = self.tlog
        if tlog is not None and self.log_raw:
            tlog.log_array(FMT_RAW, data, t_ns=t_ns)
        got_fast = 0
        state = self.ctx.state
        sink = self.item_sink
        for item in self.decoder.feed(data, t_ns):
            if sink is not None:
                sink(item)
            if isinstance(item, ImuFast):
                got_fast += 1
                sample = ImuSample(t_ns, item.counter, item.rates_rad_s, item.accel_m_s2,
                                   item.gyro_ok, item.accel_ok)
                state.imu.write(sample)
                state.imu_stream.put(sample)
                if tlog is not None:
                    tlog.log(FMT_FAST, item.counter, item.status, *item.rates_rad_s,
                             *item.accel_m_s2, t_ns=t_ns)
            elif isinstance(item, ImuSlow):
                state.imu_slow.write(ImuSlowSample(t_ns, item.rates_rad_s, item.accel_m_s2,
                                                   item.temperature_c, item.bit_word))
                if tlog is not None:
                    tlog.log(FMT_SLOW, *item.rates_rad_s, *item.accel_m_s2, item.temperature_c,
                             item.bit_word, t_ns=t_ns)
        return got_fast

    def counters(self) -> dict[str, int]:
        out = super().counters()
        out.update({k: getattr(self.decoder.counters, k) for k in
                    ("frames_good", "bad_checksum", "bad_field", "resyncs", "bytes_discarded",
                     "slow_good", "slow_dropped")})
        return out
