from __future__ import annotations

import math
import os
import select
import time

import numpy as np
import pytest

from companion.drivers.gps_protocol import NmeaDecoder
from companion.drivers.gps_solution import GpsSolution
from companion.drivers.imu_protocol import ImuDecoder, ImuFast, ImuSlow
from companion.drivers.servo_protocol import (
    PilotDecoder,
    PilotFrame,
    ServoCommand,
    encode_command,
)
from companion.sim.byte_faults import FaultInjector
from companion.sim.faults import FaultPlan
from companion.sim.gps_sim import GpsSim, GpsSimConfig
from companion.sim.imu_model import ImuSimConfig
from companion.sim.imu_sim import ImuSim
from companion.sim.servo_sim import ServoBoardConfig, ServoBoardSim

RATES = (0.1, -0.05, 0.3)
ACCEL = (0.5, -0.2, -9.81)


def rng(seed: int = 1) -> np.random.Generator:
    return np.random.default_rng(seed)


def imu_stream(sim: ImuSim, frames: int) -> list[bytes]:
    return [sim.frame(RATES, ACCEL) for _ in range(frames)]


# --- IMU ---------------------------------------------------------------------------------------


def test_imu_sim_is_deterministic_for_a_seed() -> None:
    assert imu_stream(ImuSim(rng(3)), 150) == imu_stream(ImuSim(rng(3)), 150)
    assert imu_stream(ImuSim(rng(3)), 5) != imu_stream(ImuSim(rng(4)), 5)


def test_imu_sim_frames_carry_truth_plus_bias_and_noise() -> None:
    sim = ImuSim(rng(), ImuSimConfig(gyro_bias_walk_rad_s_sqrt_s=0, accel_bias_walk_m_s2_sqrt_s=0))
    decoder = ImuDecoder()
    out = decoder.feed(b"".join(imu_stream(sim, 1000)), 0)
    fast = [x for x in out if isinstance(x, ImuFast)]
    assert [f.counter for f in fast] == [n % 100 for n in range(1000)]
    assert all(f.gyro_ok and f.accel_ok and not f.self_test for f in fast)
    rates = np.array([f.rates_rad_s for f in fast])
    accel = np.array([f.accel_m_s2 for f in fast])
    # the mean converges on truth + turn-on bias, the spread on the configured noise
    assert rates.mean(axis=0) == pytest.approx(np.add(RATES, sim.gyro_bias_rad_s), abs=3e-4)
    assert accel.mean(axis=0) == pytest.approx(np.add(ACCEL, sim.accel_bias_m_s2), abs=3e-3)
    assert rates.std(axis=0) == pytest.approx([0.003] * 3, rel=0.15)
    assert np.abs(sim.gyro_bias_rad_s).max() > 0  # a bias was drawn at all
    assert decoder.counters.slow_good == 10 and decoder.counters.bad_checksum == 0


def test_imu_sim_quantises_like_the_device() -> None:
    sim = ImuSim(rng(), ImuSimConfig(gyro_noise_rad_s=0, gyro_bias_sigma_rad_s=0,
                                      gyro_bias_walk_rad_s_sqrt_s=0))  # fmt: skip
    frame = ImuDecoder().feed(sim.frame((math.radians(1.011), 0, 0), ACCEL), 0)[0]
    assert isinstance(frame, ImuFast)
    assert frame.rates_rad_s[0] == pytest.approx(math.radians(1.02))  # 0.02 deg/s steps


def test_imu_slow_block_carries_the_previous_cycle_mean() -> None:
    sim = ImuSim(rng(), ImuSimConfig(temperature_c=41.5, bit_word=0x0004))
    out = ImuDecoder().feed(b"".join(imu_stream(sim, 300)), 0)
    slow = [x for x in out if isinstance(x, ImuSlow)]
    assert len(slow) == 3
    assert slow[0].temperature_c == pytest.approx(41.5) and slow[0].bit_word == 4
    # cycle 2's block is the mean of cycle 1's measurements: within a few noise/sqrt(100) of truth
    assert slow[1].rates_rad_s == pytest.approx(np.add(RATES, sim.gyro_bias_rad_s), abs=2e-3)
    assert slow[2].accel_m_s2 == pytest.approx(np.add(ACCEL, sim.accel_bias_m_s2), abs=2e-2)


def test_imu_self_test_frames() -> None:
    sim = ImuSim(rng(), ImuSimConfig(self_test_frames=3))
    out = ImuDecoder().feed(b"".join(imu_stream(sim, 5)), 0)
    assert [(f.self_test, f.gyro_ok) for f in out if isinstance(f, ImuFast)] == [
        (True, False), (True, False), (True, False), (False, True), (False, True)
    ]  # fmt: skip


def test_imu_sim_rejects_bad_truth() -> None:
    with pytest.raises(ValueError, match="rates_rad_s"):
        ImuSim(rng()).frame((0.0, math.nan, 0.0), ACCEL)
    with pytest.raises(ValueError, match="accel_m_s2"):
        ImuSim(rng()).frame(RATES, (0.0, 0.0))


# --- GPS ---------------------------------------------------------------------------------------

LAT, LON, ALT = 45.0, 9.0, 300.0


def gps_epochs(sim: GpsSim, count: int, t0: float = 3600.0) -> list[bytes]:
    return [sim.epoch(t0 + k / 10, LAT, LON, ALT, 20.0, -5.0, -1.0) for k in range(count)]


def test_gps_sim_epochs_decode_close_to_truth() -> None:
    config = GpsSimConfig()
    sim = GpsSim(rng(), config)
    decoder = NmeaDecoder(expected_sentences=config.expected_sentences)
    solutions: list[GpsSolution] = []
    for k, data in enumerate(gps_epochs(sim, 200)):
        got = decoder.feed(data, k)
        assert len(got) == 1  # the expected set completes each epoch at once
        solutions += got
    assert decoder.counters.sentences_good == 1000 and decoder.counters.bytes_discarded == 0
    north_m = np.array([(s.lat_deg - LAT) * 111_132 for s in solutions])  # type: ignore[operator]
    up_m = np.array([s.alt_m - ALT for s in solutions])  # type: ignore[operator]
    assert np.abs(north_m).max() < 8 and np.abs(up_m).max() < 12
    assert north_m.std() > 0.3  # white noise is there
    vn = np.array([s.vn_m_s for s in solutions])
    assert vn.mean() == pytest.approx(20.0, abs=0.02)
    first = solutions[0]
    assert (first.fix, first.sats, first.hdop, first.pdop, first.vdop) == (1, 9, 0.9, 1.6, 1.3)
    assert first.utc == pytest.approx(3600.0) and first.alt_std_m == pytest.approx(1.51, abs=0.01)


def test_gps_sim_random_walk_wanders() -> None:
    config = GpsSimConfig(horiz_white_m=0.0, vert_white_m=0.0, horiz_walk_m_sqrt_s=1.0)
    sim = GpsSim(rng(), config)
    gps_epochs(sim, 600)
    assert sim.last_solution is not None and sim.last_solution.lat_deg is not None
    assert abs(sim.last_solution.lat_deg - LAT) * 111_132 > 0.5  # sigma ~7.7 m after 60 s


def test_gps_sim_options_talker_pashr_geoid_and_no_fix() -> None:
    config = GpsSimConfig(talker="GN", ashtech_pos=True, geoid_sep_m=47.0, sentences=("GGA",))
    data = GpsSim(rng(), config).epoch(10.0, LAT, LON, ALT, 0.0, 0.0, 2.0)
    assert data.startswith(b"$GNGGA,") and b"$PASHR,POS," in data
    (sol,) = NmeaDecoder(expected_sentences=config.expected_sentences).feed(data, 0)
    assert sol.alt_ellipsoid_m == pytest.approx(sol.alt_m + 47.0, abs=0.02)  # type: ignore[operator]
    assert sol.vd_m_s == pytest.approx(2.0, abs=0.3)
    blind = GpsSim(rng(), GpsSimConfig(fix=0)).epoch(10.0, LAT, LON, ALT, 0.0, 0.0, 0.0)
    decoder = NmeaDecoder()
    decoder.feed(blind, 0)
    (none,) = decoder.flush(1)
    assert none.fix == 0 and none.lat_deg is None and none.speed_m_s is None


def test_gps_sim_date_rolls_over_and_is_deterministic() -> None:
    a = GpsSim(rng(5)).epoch(86400.5, LAT, LON, ALT, 1.0, 1.0, 0.0)
    assert a == GpsSim(rng(5)).epoch(86400.5, LAT, LON, ALT, 1.0, 1.0, 0.0)
    assert b",000000.50," in a and b",020603," in a
    with pytest.raises(ValueError, match="finite"):
        GpsSim(rng()).epoch(0.0, math.inf, LON, ALT, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="talker"):
        GpsSim(rng(), GpsSimConfig(talker="XX"))


# --- servo board -------------------------------------------------------------------------------

PILOT_MANUAL = (1400, 1450, 1300, 1550, 1100, 1500, 1500, 1500)
PILOT_AUTO = (1400, 1450, 1300, 1550, 1900, 1500, 1500, 1500)
COMPUTER = (1800, 1200, 1700, 0, 0, 0, 0, 0)


def exchange(board: ServoBoardSim, seq: int, auto: bool, t_s: float) -> list[PilotFrame]:
    reply = board.feed(encode_command(ServoCommand(seq, auto, COMPUTER)), t_s)
    return PilotDecoder().feed(reply, 0)


def test_board_answers_each_command_echoing_seq() -> None:
    board = ServoBoardSim(rng())
    board.set_pilot(PILOT_MANUAL)
    stream = b"".join(encode_command(ServoCommand(seq, False, COMPUTER)) for seq in (7, 8, 9))
    reply = board.feed(stream[:30], 0.0) + board.feed(stream[30:], 0.02)
    frames = PilotDecoder().feed(reply, 0)
    assert [f.seq for f in frames] == [7, 8, 9]
    assert all(f.channels_us == PILOT_MANUAL and not f.auto_engaged for f in frames)
    assert board.answered == 3 and board.last_command is not None
    assert board.feed(b"", 0.04) == b""  # the board never speaks first


@pytest.mark.parametrize(
    ("pilot", "asked", "computer_drives"),
    [(PILOT_MANUAL, False, False), (PILOT_MANUAL, True, False), (PILOT_AUTO, False, False),
     (PILOT_AUTO, True, True)],
)  # fmt: skip
def test_board_rule_pilot_switch_and_computer_request(
    pilot: tuple[int, ...], asked: bool, computer_drives: bool
) -> None:
    board = ServoBoardSim(rng())
    board.set_pilot(pilot)
    (frame,) = exchange(board, 1, asked, 0.0)
    assert frame.auto_engaged == (pilot[4] > 1700)
    assert board.auto_active(0.0) == computer_drives
    effective = board.effective_channels_us(0.0)
    if computer_drives:
        # channels the computer left at 0, and the mode switch, stay with the pilot
        assert effective == (1800, 1200, 1700, 1550, 1900, 1500, 1500, 1500)
    else:
        assert effective == pilot


def test_board_falls_back_to_pilot_when_commands_stop_or_pilot_takes_over() -> None:
    board = ServoBoardSim(rng(), ServoBoardConfig(command_timeout_s=0.1))
    board.set_pilot(PILOT_AUTO)
    exchange(board, 1, True, 1.0)
    assert board.auto_active(1.05) and not board.auto_active(1.2)
    board.set_pilot(PILOT_MANUAL)
    assert board.effective_channels_us(1.05) == PILOT_MANUAL


def test_board_failsafe_flag_and_batteries_drain() -> None:
    board = ServoBoardSim(rng(), ServoBoardConfig(batt_noise_raw=0.0, servo_drain_raw_per_h=30))
    board.set_pilot(PILOT_MANUAL, failsafe=True)
    (start,) = exchange(board, 1, False, 0.0)
    (later,) = exchange(board, 2, False, 3600.0)
    assert start.failsafe and (start.avionics_batt_raw, start.servo_batt_raw) == (100, 98)
    assert (later.avionics_batt_raw, later.servo_batt_raw) == (92, 68)
    with pytest.raises(ValueError, match="8 values"):
        board.set_pilot((1500,) * 4)


def test_board_survives_garbage_in_the_command_stream() -> None:
    board = ServoBoardSim(rng())
    good = encode_command(ServoCommand(5, True, COMPUTER))
    reply = board.feed(b"\xa5\x5a\x00garbage" + good[:9] + good, 0.0)
    assert [f.seq for f in PilotDecoder().feed(reply, 0)] == [5]
    assert board.decoder.counters.bytes_discarded == 10 + 9


# --- fault injection ---------------------------------------------------------------------------


def test_fault_plan_validation() -> None:
    with pytest.raises(ValueError, match="cut_prob"):
        FaultPlan(cut_prob=1.5)
    with pytest.raises(ValueError, match="garbage_len"):
        FaultPlan(garbage_len=(0, 3))
    with pytest.raises(ValueError, match="silence_s"):
        FaultPlan(silence_s=((2.0, 1.0),))


def run_imu_with_faults(plan: FaultPlan, frames: int = 1000, chunk: int = 0) -> tuple[
    list[bytes], list[ImuFast | ImuSlow], ImuDecoder, FaultInjector
]:  # fmt: skip
    sent = imu_stream(ImuSim(rng(11)), frames)
    injector = FaultInjector(plan, rng(12))
    wire = b"".join(injector.apply(f, k / 100) for k, f in enumerate(sent))
    decoder = ImuDecoder()
    if chunk:
        out = [x for i in range(0, len(wire), chunk) for x in decoder.feed(wire[i : i + chunk], i)]
    else:
        out = decoder.feed(wire, 0)
    return sent, out, decoder, injector


def test_garbage_bursts_never_cost_a_real_frame() -> None:
    sent, out, decoder, injector = run_imu_with_faults(
        FaultPlan(garbage_prob=0.3, garbage_len=(1, 40))
    )
    fast = [x for x in out if isinstance(x, ImuFast)]
    assert injector.counts.garbage_bursts > 200
    assert len(fast) == len(sent) and decoder.counters.frames_good == len(sent)
    assert decoder.counters.bytes_discarded == injector.counts.garbage_bytes
    assert decoder.counters.slow_good == 10  # nothing missing: every cycle reconstructs


@pytest.mark.parametrize("chunk", [0, 1, 7])
def test_cut_frames_are_counted_and_the_rest_decodes(chunk: int) -> None:
    sent, out, decoder, injector = run_imu_with_faults(FaultPlan(cut_prob=0.05), chunk=chunk)
    cuts = injector.counts.cut
    assert cuts > 20
    assert decoder.counters.frames_good == len(sent) - cuts
    assert decoder.counters.slow_good + decoder.counters.slow_dropped == 10
    assert decoder.counters.slow_dropped >= 1


def test_bad_checksums_are_never_passed_on() -> None:
    sent, out, decoder, injector = run_imu_with_faults(FaultPlan(bad_checksum_prob=0.1))
    good = {ImuDecoder().feed(f, 0)[0] for f in sent}
    fast = [x for x in out if isinstance(x, ImuFast)]
    assert injector.counts.corrupted > 50
    assert len(fast) == len(sent) - injector.counts.corrupted
    assert all(f in good for f in fast)
    assert decoder.counters.bad_checksum + decoder.counters.bad_field >= injector.counts.corrupted


def test_silence_window_drops_bytes_and_the_slow_block() -> None:
    sent, out, decoder, injector = run_imu_with_faults(FaultPlan(silence_s=((2.5, 3.0),)))
    assert injector.counts.silenced == 50
    assert decoder.counters.frames_good == len(sent) - 50
    assert decoder.counters.slow_dropped == 1 and decoder.counters.slow_good == 9


def test_every_fault_at_once_on_gps_and_servo_streams() -> None:
    plan = FaultPlan(garbage_prob=0.2, cut_prob=0.1, bad_checksum_prob=0.2, silence_s=((5.0, 6.0),))
    gps = GpsSim(rng(2))
    injector = FaultInjector(plan, rng(3))
    decoder = NmeaDecoder()
    truth: dict[int, GpsSolution] = {}
    out: list[GpsSolution] = []
    for k in range(100):
        data = gps.epoch(k / 10, LAT, LON, ALT, 10.0, 0.0, 0.0)
        assert gps.last_solution is not None
        truth[k] = gps.last_solution
        out += decoder.feed(injector.apply(data, k / 10), k)
    out += decoder.flush(100)
    assert 70 < len(out) < 100
    for sol in out:
        assert sol.utc is not None
        ref = truth[round(sol.utc * 10)]
        if sol.lat_deg is not None:
            assert sol.lat_deg == pytest.approx(ref.lat_deg, abs=1e-6)
    c = decoder.counters
    assert c.bad_checksum + c.cut > 0 and c.bytes_discarded > 0

    board = ServoBoardSim(rng())
    injector = FaultInjector(plan, rng(4))
    replies = b""
    for seq in range(200):
        command = encode_command(ServoCommand(seq, True, COMPUTER))
        replies += board.feed(injector.apply(command, seq / 50), seq / 50)
    answered = [f.seq for f in PilotDecoder().feed(replies, 0)]
    assert answered == sorted(answered) and 100 < len(answered) < 200
    assert board.answered == len(answered)


# --- through a real pseudo-terminal ------------------------------------------------------------


def test_sim_bytes_through_a_pseudo_terminal() -> None:
    import tty

    master, slave = os.openpty()
    try:
        tty.setraw(slave)
        sent = imu_stream(ImuSim(rng()), 200)
        decoder = ImuDecoder()
        out: list[ImuFast | ImuSlow] = []
        deadline = time.monotonic() + 5.0
        for frame in sent:
            os.write(master, frame)
        while len(out) < 202 and time.monotonic() < deadline:
            ready, _, _ = select.select([slave], [], [], 0.1)
            if ready:
                out += decoder.feed(os.read(slave, 4096), time.monotonic_ns())
        assert len(out) == 202  # 200 fast frames, 2 slow blocks
        assert decoder.counters.bytes_discarded == 0
    finally:
        os.close(master)
        os.close(slave)


def test_a_uart_at_the_right_rate_reads_the_bytes_unchanged() -> None:
    from companion.sim.byte_faults import uart_misread

    data = bytes(range(256))
    assert uart_misread(data, 1.0) == data
    assert uart_misread(data, 1.02) == data  # 2 % is within a UART's tolerance


@pytest.mark.parametrize("ratio", [0.5, 2.0, 8.0])
def test_a_wrong_baud_rate_yields_bytes_that_never_frame(ratio: float) -> None:
    """What a mismatched UART receives from a stream of good IMU frames: bytes keep coming
    (the driver can tell a wrong rate from a silent device) and no frame decodes."""
    from companion.sim.byte_faults import uart_misread

    frames = imu_stream(ImuSim(rng(5)), 300)
    received = b"".join(uart_misread(f, ratio) for f in frames)
    assert len(received) > 0.05 * sum(map(len, frames))
    decoder = ImuDecoder()
    out = decoder.feed(received, 0)
    assert not [x for x in out if isinstance(x, ImuFast)]


def test_a_flood_sends_every_chunk_n_times_only_inside_its_window() -> None:
    inj = FaultInjector(FaultPlan(flood_s=((1.0, 2.0),), flood_factor=10), rng(2))
    assert inj.apply(b"abc", 0.5) == b"abc"
    assert inj.apply(b"abc", 1.5) == b"abc" * 10
    assert inj.apply(b"abc", 2.0) == b"abc"
    assert inj.counts.flooded == 9


def test_device_fault_specs_parse_and_bad_ones_name_the_item() -> None:
    from companion.sim.faults import parse_fault, parse_vanish

    dev, plan = parse_fault("gps:utcstep=30:-1,flood=5-8,floodx=3,wrongbaud=1-2,baudratio=0.5")
    assert dev == "gps" and plan.utc_step_s == ((30.0, -1.0),) and plan.flood_factor == 3
    assert plan.flood_s == ((5.0, 8.0),) and plan.wrong_baud_s == ((1.0, 2.0),)
    assert parse_vanish("imu:3:1:renamed").renamed and not parse_vanish("imu:3:1").renamed
    for bad, words in [("imu:utcstep=3:1", "unknown key 'utcstep'"),
                       ("imu:flood=x-2", "'flood=x-2'"), ("imu:baudratio=1", "baud_ratio"),
                       ("imu:floodx=1", "flood_factor")]:
        with pytest.raises(ValueError, match=words):
            parse_fault(bad)
    with pytest.raises(ValueError, match="renamed"):
        parse_vanish("imu:3:1:gone")
