"""Servo-board driver thread: every 20 ms send the computer's command, then read the pilot's.

The computer sends first and then reads, as the board expects. The computer asks for automatic
control only while the control law is enabled and producing fresh output; the board itself
decides, from the pilot's mode switch, whether to obey, so the pilot can always take over.
"""

from __future__ import annotations

from typing import Any

from companion.core.params import ParamSpec, int_param
from companion.core.state import ControlOutput, ServoState
from companion.drivers.serial_device import SerialDevice
from companion.drivers.servo_protocol import (
    CH_THROTTLE,
    CHANNELS,
    PilotDecoder,
    PilotFrame,
    ServoCommand,
    encode_command,
    pilot_switch_auto,
    surfaces_to_channels,
    us_to_throttle,
)
from companion.watchdog.task import Task

FMT_EXCHANGE = 1
CONTROL_FRESH_S = 0.1  # older control output is not sent: the board falls back to the pilot


def surfaces_to_us(out: ControlOutput) -> tuple[int, ...]:
    """Normalised surfaces to pulse widths (+-1 -> 1000..2000 us, throttle 0..1 -> 1000..2000),
    the same mapping the pilot's transmitter uses."""

    return (*surfaces_to_channels(out.aileron, out.elevator, out.rudder, out.throttle),
            0, 0, 0, 0)


def define_exchange_log(tlog: Any) -> None:
    """The format of ``servo.bin``'s exchanges, whoever produces them (this driver, or an
    autopilot link whose RC input and outputs take the slot)."""
    cols = ([f"pilot{i}_us" for i in range(1, 9)] + [f"cmd{i}_us" for i in range(1, 9)]
            + ["seq", "auto_requested", "auto_engaged", "failsafe", "avionics_batt",
               "servo_batt"])
    tlog.define(FMT_EXCHANGE, ",".join(["%hu"] * 16) + ",%hhu,%hhu,%hhu,%hhu,%hhu,%hhu", cols)


class ServoDriver(SerialDevice):
    """Writes the command, then reads the pilot's answer: a timer thread, not a paced reader,
    so it overrides `step` and publishes each answer through `publish`."""

    def __init__(self, url: str, baudrate: int = 115200, *, task: Task) -> None:
        super().__init__(task, url=url, baudrate=baudrate, read_timeout_s=0.005)
        self.decoder = PilotDecoder()
        self.seq = 0
        self.answer_timeout_s = 0.015
        self.missed_answers = 0
        self.match_seq = True  # replaying a capture: accept answers to commands never sent
        self._last_cmd: ServoCommand | None = None  # the previous command, while unanswered

    @classmethod
    def declare_params(cls, prefix: str) -> list[ParamSpec]:
        return super().declare_params(prefix) + [int_param(f"{prefix}_ANS_MS", 15, 1, 19, "ms",
                          "How long to wait for the board's pilot frame after each command.")]

    def define_logs(self, tlog: Any) -> None:
        define_exchange_log(tlog)
        super().define_logs(tlog)

    def configure(self) -> None:
        super().configure()
        self.answer_timeout_s = int(self.param("ANS_MS")) / 1000.0

    def prepare_for_replay(self) -> None:
        self.match_seq = False  # a capture answers commands this driver never sent

    def on_port_opened(self) -> None:
        self.decoder.reset()

    def recover(self) -> None:
        self.decoder.reset()

    def _command(self) -> ServoCommand:
        now_ns = self.ctx.clock.realtime_ns()
        out = self.ctx.state.control.read()
        if out is not None and out.enabled and (now_ns - out.t_ns) < CONTROL_FRESH_S * 1e9:
            return ServoCommand(self.seq, True, surfaces_to_us(out))
        return ServoCommand(self.seq, False, (0,) * CHANNELS)

    def step(self) -> int:
        self.seq = (self.seq + 1) & 0xFF
        cmd = self._command()
        if self.ensure_port() is None or not self.write(encode_command(cmd)):
            return 0
        clock = self.ctx.clock
        deadline_ns = clock.monotonic_ns() + int(self.answer_timeout_s * 1e9)
        answered = 0
        got_current = False
        while (not got_current and clock.monotonic_ns() < deadline_ns
               and not self.stop_requested):
            data = self.read_chunk()
            if not data:
                continue
            for frame in self.decoder.feed(data, clock.realtime_ns()):
                if self.item_sink is not None:
                    self.item_sink(frame)
                current = frame.seq == cmd.seq or not self.match_seq
                # An answer to the previous command that came late is still the pilot's real
                # input: publish and log it rather than lose an exchange.
                late = frame.seq == ((cmd.seq - 1) & 0xFF) and self._last_cmd is not None
                if current or late:
                    sent = cmd if current else self._last_cmd
                    assert sent is not None
                    answered += self.publish((frame, sent), clock.realtime_ns())
                    got_current = got_current or current
        self._last_cmd = cmd if not got_current else None
        if not got_current:
            self.missed_answers += 1
        return answered

    def publish(self, item: object, t_ns: int) -> int:
        """One exchange: the pilot's answer with the command it answers."""
        assert isinstance(item, tuple)
        answer: PilotFrame = item[0]
        cmd: ServoCommand = item[1]
        self.ctx.state.servo.write(ServoState(
            t_ns, cmd.seq, answer.channels_us, cmd.channels_us, cmd.auto_requested,
            answer.auto_engaged, answer.failsafe, answer.avionics_batt_raw, answer.servo_batt_raw,
            pilot_switch_auto(answer.channels_us), us_to_throttle(answer.channels_us[CH_THROTTLE])))
        if self.tlog is not None:
            self.tlog.log(FMT_EXCHANGE, *answer.channels_us, *cmd.channels_us, cmd.seq,
                          int(cmd.auto_requested), int(answer.auto_engaged), int(answer.failsafe),
                          answer.avionics_batt_raw, answer.servo_batt_raw, t_ns=t_ns)
        return 1

    def counters(self) -> dict[str, int]:
        out = super().counters()
        out.update({k: getattr(self.decoder.counters, k) for k in
                    ("frames_good", "bad_checksum", "bad_field", "resyncs", "bytes_discarded")})
        out["missed_answers"] = self.missed_answers
        return out
