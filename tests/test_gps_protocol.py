"""NMEA/Ashtech decoder tests.

``tests/data/gps_gn_ashtech_capture.nmea`` is 2 s (20 epochs at 10 Hz) of a multi-GNSS receiver
with Ashtech output, written by a small script independent of ``encode_epoch`` (7-decimal minutes,
NMEA 4.10 GSA with a system id, DGPS fix): power-up NULs, GNGGA/GNRMC/GNVTG/2xGNGSA/GNGST and
``$PASHR,POS`` every epoch, GSV and ``$PASHR,SAT`` every 5th, a GPGGA alongside the GNGGA in epoch
7, ``$PASHR,RID``/``ACK`` in epoch 12, the attitude ``$PASHR`` and an Ashtech binary chunk in
epoch 15, a ``$$`` in epoch 3. The track: 2.0 m north, 1.5 m east, 0.2 m up per epoch.
"""

from __future__ import annotations

import datetime as dt
import json
import math
from functools import reduce
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.drivers.gps_encoder import encode_epoch
from companion.drivers.gps_protocol import MAX_LINE_CHARS, NmeaDecoder
from companion.drivers.gps_solution import GpsSolution
from companion.drivers.nmea_fields import KNOTS_TO_M_S, nmea_sentence

CAPTURE = (Path(__file__).parent / "data" / "gps_gn_ashtech_capture.nmea").read_bytes()
ALL = ["GGA", "RMC", "VTG", "GSA", "GST", "POS"]


def s(body: str) -> bytes:
    """Independent checksum helper (not the module's) for hand-written sentences."""
    return b"$%s*%02X\r\n" % (body.encode(), reduce(lambda a, c: a ^ ord(c), body, 0))


GGA = "GPGGA,123519.00,4807.0380,N,01131.0000,E,1,08,0.9,545.4,M,46.9,M,,"
RMC = "GPRMC,123519.00,A,4807.0380,N,01131.0000,E,022.4,084.4,230394,003.1,W,A"
GGA2 = "GPGGA,123519.10,4807.0390,N,01131.0010,E,1,08,0.9,545.5,M,46.9,M,,"


def decode(data: bytes, **kwargs: object) -> tuple[list[GpsSolution], NmeaDecoder]:
    decoder = NmeaDecoder(**kwargs)  # type: ignore[arg-type]
    out = decoder.feed(data, 0)
    out += decoder.flush(1)
    return out, decoder


# --- the realistic capture ---------------------------------------------------------------------


@pytest.mark.parametrize("expected", [None, ALL])
@pytest.mark.parametrize("chunk", [1, 37, len(CAPTURE)])
def test_capture_decodes_every_epoch(expected: list[str] | None, chunk: int) -> None:
    decoder = NmeaDecoder(expected_sentences=expected)
    out: list[GpsSolution] = []
    for i in range(0, len(CAPTURE), chunk):
        out += decoder.feed(CAPTURE[i : i + chunk], i)
    if expected is None:
        assert len(out) == 19  # the last epoch waits for the next one or a flush
    out += decoder.flush(len(CAPTURE))
    assert len(out) == 20
    assert [round(x.utc * 10) for x in out if x.utc is not None] == list(range(369300, 369320))
    first = out[0]
    assert first.lat_deg == pytest.approx(45 + 28.12344 / 60, abs=1e-9)
    assert first.lon_deg == pytest.approx(9 + 10.98768 / 60, abs=1e-9)
    assert (first.alt_m, first.alt_ellipsoid_m, first.geoid_sep_m) == pytest.approx(
        (250.0, 297.3, 47.3)
    )
    assert (first.fix, first.sats, first.hdop, first.pdop, first.vdop, first.tdop) == (
        2,
        14,
        0.7,
        1.3,
        1.1,
        0.9,
    )
    assert first.speed_m_s == pytest.approx(48.60 * KNOTS_TO_M_S)
    assert first.course_deg == pytest.approx(36.87)
    assert (first.vn_m_s, first.ve_m_s, first.vd_m_s) == pytest.approx((20.0, 15.0, -2.0), abs=0.01)
    assert first.alt_std_m == pytest.approx(1.6) and first.date == dt.date(2003, 6, 21)
    for k, sol in enumerate(out):
        north_m = (sol.lat_deg - first.lat_deg) * 111320.0  # type: ignore[operator]
        assert north_m == pytest.approx(2.0 * k, abs=0.01)
        assert sol.alt_m == pytest.approx(250.0 + 0.2 * k)
    # epoch 7 also had a GPGGA (3 m higher): the GN solution wins
    assert out[7].sentences[:2] == ("GPGGA", "GNGGA") and out[7].alt_m == pytest.approx(251.4)
    c = decoder.counters
    assert (c.sentences_good, c.unknown, c.too_long, c.malformed, c.late, c.epochs) == (
        141,
        27,
        0,
        0,
        0,
        20,
    )
    # the binary chunk: it holds a non-text byte (cut) and a '$*A' (a bad checksum)
    assert (c.cut, c.bad_checksum) == (1, 1)


def test_capture_latency_when_expected_set_completes_the_epoch() -> None:
    decoder = NmeaDecoder(expected_sentences=ALL)
    out: list[GpsSolution] = []
    for i in range(len(CAPTURE)):  # byte i arrives at i microseconds
        out += decoder.feed(CAPTURE[i : i + 1], i * 1000)
    for sol in out:
        assert sol.first_byte_t_ns is not None and sol.handoff_t_ns is not None
        assert CAPTURE[sol.first_byte_t_ns // 1000] == ord("$")
        # handed off on the last checksum digit of $PASHR,POS, not when the next epoch starts
        last = sol.handoff_t_ns // 1000
        assert CAPTURE[last - 2] == ord("*")
        assert CAPTURE[CAPTURE.rfind(b"$", 0, last) :].startswith(b"$PASHR,POS")
        assert sol.latency_s == pytest.approx((sol.handoff_t_ns - sol.first_byte_t_ns) / 1e9)


# --- epoch grouping and latency -----------------------------------------------------------------


def test_epoch_is_handed_off_when_the_next_one_starts() -> None:
    decoder = NmeaDecoder()
    assert decoder.feed(s(GGA)[:30], 1_000) == []
    assert decoder.feed(s(GGA)[30:] + s(RMC), 2_000) == []
    out = decoder.feed(s(GGA2), 5_000)
    assert len(out) == 1
    sol = out[0]
    assert sol.utc == pytest.approx(12 * 3600 + 35 * 60 + 19)
    assert sol.first_byte_t_ns == 1_000 and sol.handoff_t_ns == 5_000
    assert sol.latency_s == pytest.approx(4e-6)
    assert sol.sentences == ("GPGGA", "GPRMC")
    assert sol.speed_m_s == pytest.approx(22.4 * KNOTS_TO_M_S)
    assert sol.date == dt.date(1994, 3, 23)
    assert sol.utc_datetime == dt.datetime(1994, 3, 23, 12, 35, 19, tzinfo=dt.UTC)
    (last,) = decoder.flush(6_000)
    assert last.utc is not None and sol.utc is not None
    assert last.utc == pytest.approx(sol.utc + 0.1) and last.latency_s == pytest.approx(1e-6)
    assert decoder.flush(7_000) == []


def test_untimed_sentences_join_the_open_or_the_next_epoch() -> None:
    gsa = "GPGSA,A,3,04,05,09,12,,,,,,,,,2.5,1.3,2.1"
    vtg = "GPVTG,054.7,T,034.4,M,005.5,N,010.2,K,A"
    # GSA before the timed sentences: belongs to the epoch it precedes, and starts its clock
    out, _ = decode(s(gsa) + s(GGA) + s(vtg))
    (sol,) = out
    assert sol.pdop == 2.5 and sol.course_deg == pytest.approx(54.7)
    assert sol.speed_m_s == pytest.approx(5.5 * KNOTS_TO_M_S)
    assert sol.sentences == ("GPGSA", "GPGGA", "GPVTG") and sol.first_byte_t_ns == 0


def test_poll_hands_off_after_the_line_goes_quiet() -> None:
    decoder = NmeaDecoder(idle_handoff_ms=20)
    decoder.feed(s(GGA), 0)
    assert decoder.poll(19_000_000) == []
    (sol,) = decoder.poll(20_000_000)
    assert sol.latency_s == pytest.approx(0.02)
    assert NmeaDecoder().poll(10**12) == []  # disabled by default


def test_late_sentence_after_hand_off_is_counted_not_turned_into_an_epoch() -> None:
    decoder = NmeaDecoder(expected_sentences=["GGA"])
    out = decoder.feed(s(GGA) + s(RMC) + s(GGA2), 0)
    assert len(out) == 2 and decoder.counters.late == 1
    # a repeated sentence with the same time (a receiver whose clock stands still) is a new epoch
    out = decoder.feed(s(GGA2), 0)
    assert len(out) == 1 and out[0].utc == pytest.approx(45319.1)


def test_gga_from_two_talkers_prefers_gn_whatever_the_order() -> None:
    gn = GGA.replace("GPGGA", "GNGGA").replace("545.4", "600.0")
    for data in (s(GGA) + s(gn), s(gn) + s(GGA)):
        (sol,), decoder = decode(data)
        assert sol.alt_m == 600.0 and decoder.counters.sentences_good == 2
    (only_gp,), _ = decode(s(GGA))
    assert only_gp.alt_m == 545.4


# --- the odd things receivers do --------------------------------------------------------------


def test_sentences_joined_without_line_ends() -> None:
    data = s(GGA).rstrip() + s(RMC).rstrip() + s(GGA2).rstrip()
    out, decoder = decode(data)
    assert len(out) == 2 and decoder.counters.sentences_good == 3
    assert decoder.counters.bytes_discarded == 0


def test_nul_bytes_between_and_inside_sentences_are_dropped() -> None:
    gga = s(GGA)
    data = b"\x00\x00" + gga[:20] + b"\x00" + gga[20:] + b"\x00" * 5 + s(RMC)
    (sol,), decoder = decode(data)
    assert sol.sentences == ("GPGGA", "GPRMC")
    assert decoder.counters.bytes_discarded == 8


def test_double_dollar_prefix() -> None:
    (sol,), decoder = decode(b"$" + s(GGA) + b"$$" + s(RMC))
    assert sol.sentences == ("GPGGA", "GPRMC")
    assert decoder.counters.cut == 0 and decoder.counters.bytes_discarded == 3


def test_sentence_cut_by_another() -> None:
    data = s(GGA)[:25] + s(RMC) + s(GGA)[:10] + b"\r\n" + s(GGA2)
    out, decoder = decode(data)
    assert [x.sentences for x in out] == [("GPRMC",), ("GPGGA",)]
    assert decoder.counters.cut == 1 and decoder.counters.bad_checksum == 1  # the one ended by CRLF


def test_sentence_without_checksum_needs_permission() -> None:
    data = b"$" + GGA.encode() + b"\r\n"
    out, decoder = decode(data)
    assert out == [] and decoder.counters.bad_checksum == 1
    (sol,), decoder = decode(data, allow_no_checksum=True)
    assert sol.alt_m == 545.4 and decoder.counters.sentences_good == 1
    # without a checksum and without a line end it is indistinguishable from a cut one
    out, decoder = decode(b"$" + GGA.encode() + s(RMC), allow_no_checksum=True)
    assert [x.sentences for x in out] == [("GPRMC",)] and decoder.counters.cut == 1


def test_bad_checksum_and_lowercase_hex() -> None:
    good = s(GGA)
    bad = good.replace(b"545.4", b"545.5")
    (sol,), decoder = decode(bad + good)
    assert decoder.counters.bad_checksum == 1 and sol.alt_m == 545.4
    lowered = good[:-4] + good[-4:-2].lower() + b"\r\n"
    (sol,), decoder = decode(lowered)
    assert sol.alt_m == 545.4 and decoder.counters.bad_checksum == 0
    # a non-hex "checksum" does not swallow the sentence that follows it
    out, decoder = decode(b"$GPXXX,1*4" + s(GGA))
    assert len(out) == 1 and decoder.counters.bad_checksum == 1


def test_line_length_limit() -> None:
    base = GGA + "0123"
    pad = MAX_LINE_CHARS - len(s(base).rstrip())
    at_limit = s(base + "9" * pad)
    assert len(at_limit.rstrip()) == MAX_LINE_CHARS
    (sol,), decoder = decode(at_limit)
    assert decoder.counters.too_long == 0
    over = s(base + "9" * (pad + 1))
    out, decoder = decode(over + s(RMC))
    assert [x.sentences for x in out] == [("GPRMC",)] and decoder.counters.too_long == 1
    # a runaway line without any terminator is dropped as soon as it passes the limit
    decoder = NmeaDecoder()
    decoder.feed(b"$GPGGA," + b"1" * 500, 0)
    assert decoder.counters.too_long == 1 and len(decoder._buf) == 0


def test_other_ashtech_sentences_and_binary_are_skipped() -> None:
    others = [
        "PASHR,SAT,03,02,120,45,44,U,05,060,30,41,U,09,300,62,47,U",
        "PASHR,XMG,PDOP,SAT",
        "PASHR,RID,DG,GB00,_SIP____",
        "PASHR,ACK",
        "PASHR,NAK",
        "PASHR,123519.000,224.19,T,-01.26,+00.83,+00.00,0.101,0.113,0.267,1,0",
    ]
    binary = b"$PASHR,MCA,\x02\x81\xfe$\r\n\x00\x7f" + bytes(range(0x80, 0xA0)) + b"\r\n"
    data = s(GGA) + b"".join(s(o) for o in others) + binary + s(RMC)
    (sol,), decoder = decode(data)
    assert sol.sentences == ("GPGGA", "GPRMC")
    assert decoder.counters.unknown == len(others) and decoder.counters.sentences_good == 2


def test_unknown_talkers_and_sentences_are_counted() -> None:
    data = s(GGA.replace("GPGGA", "BDGGA")) + s("GPZDA,123519.00,23,03,1994,00,00") + s(GGA)
    (sol,), decoder = decode(data)
    assert decoder.counters.unknown == 2 and sol.sentences == ("GPGGA",)


def test_malformed_fields_are_rejected_not_guessed() -> None:
    no_hemisphere = GGA.replace(",N,", ",,")  # pynmea2 would read this latitude as 0 degrees
    bad_number = GGA.replace("545.4", "5x5.4")
    bad_time = GGA.replace("123519.00", "253519.00")
    for body in (no_hemisphere, bad_number, bad_time, "GPGGA", "GPRMC,1,A,,,,,,,320394"):
        out, decoder = decode(s(body))
        assert out == [] and decoder.counters.malformed == 1, body


def test_fix_mapping() -> None:
    def fix_of(body: str) -> int:
        (sol,), _ = decode(s(body))
        return sol.fix

    assert fix_of(GGA.replace(",1,08,", ",4,08,")) == 3
    assert fix_of(GGA.replace(",1,08,", ",5,08,")) == 3
    assert fix_of(GGA.replace(",1,08,", ",2,08,")) == 2
    assert fix_of(GGA.replace(",1,08,", ",6,08,")) == 0  # dead reckoning is not a fix
    assert fix_of(GGA.replace(",1,08,", ",0,08,")) == 0
    assert fix_of(RMC.replace(",A,4807", ",V,4807")) == 0
    assert fix_of(RMC[:-1] + "D") == 2


# --- Ashtech POS --------------------------------------------------------------------------------

POS = "PASHR,POS,0,07,123519.00,4807.0380,N,01131.0000,E,+00592.30,,084.40,022.40,-001.25,02.5,01.3,02.1,01.4,GB00"


def test_pashr_pos_reads_knots_ellipsoid_height_and_vertical_velocity() -> None:
    (sol,), _ = decode(s(POS))
    assert sol.speed_m_s == pytest.approx(22.4 * 1852 / 3600)  # knots, not km/h as gpsd reads it
    assert sol.course_deg == pytest.approx(84.4)
    assert sol.vd_m_s == pytest.approx(1.25)  # descending at 1.25 m/s
    assert sol.alt_ellipsoid_m == pytest.approx(592.3)
    assert sol.alt_m is None  # no geoid separation known yet: MSL unknown
    assert (sol.fix, sol.sats, sol.pdop, sol.hdop, sol.vdop, sol.tdop) == (1, 7, 2.5, 1.3, 2.1, 1.4)
    assert sol.lat_deg == pytest.approx(48 + 7.038 / 60)
    assert sol.vn_m_s == pytest.approx(22.4 * KNOTS_TO_M_S * math.cos(math.radians(84.4)))


def test_pashr_pos_altitude_uses_the_last_known_geoid_separation() -> None:
    decoder = NmeaDecoder()
    decoder.feed(s(GGA), 0)
    later = POS.replace("123519.00", "123519.10")
    (first,) = decoder.feed(s(later), 1)
    (second,) = decoder.flush(2)
    assert first.alt_m == 545.4 and first.alt_ellipsoid_m == pytest.approx(545.4 + 46.9)
    assert second.alt_m == pytest.approx(592.3 - 46.9)


def test_pashr_pos_fix_types() -> None:
    for position_type, fix in (("", 0), ("0", 1), ("1", 2), ("2", 3)):
        (sol,), _ = decode(s(POS.replace("POS,0,", f"POS,{position_type},")))
        assert sol.fix == fix


# --- JSON and encoding ------------------------------------------------------------------------


def test_json_dict_has_exactly_the_agreed_keys() -> None:
    (sol,), _ = decode(s(GGA))
    d = sol.to_json_dict()
    assert list(d) == [
        "utc", "lat_deg", "lon_deg", "alt_m", "fix", "sats", "hdop", "pdop", "vdop",
        "speed_m_s", "course_deg", "alt_std_m",
    ]  # fmt: skip
    assert json.loads(json.dumps(d)) == d
    assert d["pdop"] is None and d["sats"] == 8


def test_encoder_rejects_bad_input() -> None:
    sol = GpsSolution(utc=1.0, lat_deg=1.0, lon_deg=2.0, fix=1)
    with pytest.raises(ValueError, match="utc"):
        encode_epoch(GpsSolution(lat_deg=1.0))
    with pytest.raises(ValueError, match="talker"):
        encode_epoch(sol, talker="XX")
    with pytest.raises(ValueError, match="GSV"):
        encode_epoch(sol, sentences=("GSV",))
    with pytest.raises(ValueError, match="lat_deg"):
        encode_epoch(GpsSolution(utc=1.0, lat_deg=math.nan))
    with pytest.raises(ValueError, match="1980..2079"):
        encode_epoch(GpsSolution(utc=1.0, date=dt.date(2080, 1, 1)))
    with pytest.raises(ValueError, match="fix"):
        encode_epoch(GpsSolution(utc=1.0, fix=4))
    with pytest.raises(ValueError, match="expected_sentences"):
        NmeaDecoder(expected_sentences=["GSV"])
    assert nmea_sentence("GPGGA,") == s("GPGGA,")


def fl(low: float, high: float) -> st.SearchStrategy[float]:
    return st.floats(low, high, allow_nan=False, allow_infinity=False)


solutions = st.builds(
    GpsSolution,
    utc=fl(0, 86399.99),
    date=st.dates(dt.date(1980, 1, 1), dt.date(2079, 12, 31)),
    lat_deg=fl(-89.9, 89.9),
    lon_deg=fl(-179.9, 179.9),
    alt_m=fl(-400, 30000),
    geoid_sep_m=fl(-100, 100),
    fix=st.integers(1, 3),
    sats=st.integers(0, 40),
    hdop=fl(0.5, 50),
    pdop=fl(0.5, 50),
    vdop=fl(0.5, 50),
    tdop=fl(0.5, 50),
    speed_m_s=fl(0, 300),
    course_deg=fl(0, 359.99),
    vd_m_s=fl(-50, 50),
    alt_std_m=fl(0, 100),
)


@settings(max_examples=150, deadline=None)
@given(sol=solutions, talker=st.sampled_from(["GP", "GN", "GL", "GA", "GB"]), pos=st.booleans())
def test_encode_decode_round_trip(sol: GpsSolution, talker: str, pos: bool) -> None:
    data = encode_epoch(sol, talker=talker, ashtech_pos=pos)
    expected = ALL if pos else ALL[:-1]
    decoder = NmeaDecoder(expected_sentences=expected)
    (got,) = decoder.feed(data, 0)
    assert decoder.counters.sentences_good == len(expected)
    assert got.utc == pytest.approx(sol.utc, abs=0.006)
    assert got.date == sol.date
    assert got.lat_deg == pytest.approx(sol.lat_deg, abs=1e-6)
    assert got.lon_deg == pytest.approx(sol.lon_deg, abs=1e-6)
    assert got.alt_m == pytest.approx(sol.alt_m, abs=0.006)
    assert got.fix == sol.fix and got.sats == sol.sats
    assert (got.hdop, got.pdop, got.vdop) == pytest.approx(
        (sol.hdop, sol.pdop, sol.vdop), abs=0.006
    )
    assert got.speed_m_s == pytest.approx(sol.speed_m_s, abs=0.001)
    assert got.course_deg is not None and sol.course_deg is not None
    assert abs((got.course_deg - sol.course_deg + 180) % 360 - 180) < 0.006
    assert got.alt_std_m == pytest.approx(sol.alt_std_m, abs=0.0006)
    if pos:
        assert got.tdop == pytest.approx(sol.tdop, abs=0.06)
        assert got.vd_m_s == pytest.approx(sol.vd_m_s, abs=0.0006)
        assert got.alt_ellipsoid_m == pytest.approx(sol.alt_m + sol.geoid_sep_m, abs=0.02)  # type: ignore[operator]


def test_no_fix_epoch_encodes_empty_position() -> None:
    data = encode_epoch(GpsSolution(utc=10.0, fix=0, sats=2), ashtech_pos=True)
    (got,), _ = decode(data)
    assert got.fix == 0 and got.lat_deg is None and got.alt_m is None and got.speed_m_s is None


# --- fuzzing ------------------------------------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(chunks=st.lists(st.binary(max_size=80), max_size=30), allow=st.booleans())
def test_fuzz_random_bytes_never_raise(chunks: list[bytes], allow: bool) -> None:
    decoder = NmeaDecoder(allow_no_checksum=allow, expected_sentences=["GGA"])
    for i, chunk in enumerate(chunks):
        decoder.feed(chunk, i)
        assert len(decoder._buf) <= MAX_LINE_CHARS + 2  # a full line may await its 2 checksum digits
    decoder.flush(len(chunks))


text_noise = st.lists(st.sampled_from(list(b"$*,.0123456789ABCDEFGNPRS\r\n\x00")), max_size=200)


@settings(max_examples=200, deadline=None)
@given(noise=text_noise, allow=st.booleans())
def test_fuzz_nmea_like_noise_never_raises(noise: list[int], allow: bool) -> None:
    decoder = NmeaDecoder(allow_no_checksum=allow)
    decoder.feed(b"$GPGGA," + bytes(noise) + s(GGA), 0)
    decoder.flush(1)


@settings(max_examples=100, deadline=None)
@given(
    edits=st.lists(
        st.tuples(st.integers(0, len(CAPTURE) - 1), st.integers(1, 255)), min_size=1, max_size=20
    )
)
def test_corrupted_capture_never_yields_data_that_was_not_sent(
    edits: list[tuple[int, int]],
) -> None:
    clean, _ = decode(CAPTURE)
    by_tenth = {round(x.utc * 10): x for x in clean if x.utc is not None}
    data = bytearray(CAPTURE)
    last = -1000
    for index, flip in sorted(edits):
        if index - last > MAX_LINE_CHARS:  # one edit per sentence: two could cancel in the XOR
            data[index] ^= flip
            last = index
    out, _ = decode(bytes(data))
    for sol in out:
        if sol.utc is None:
            continue  # an epoch of untimed sentences only (its timed ones were all damaged)
        ref = by_tenth[round(sol.utc * 10)]  # a KeyError would be an invented time
        assert ref.lat_deg is not None and ref.alt_m is not None and ref.speed_m_s is not None
        if sol.lat_deg is not None:  # GGA/RMC 7 decimals of minutes, PASHR 4, GPGGA +1e-5 deg
            assert abs(sol.lat_deg - ref.lat_deg) < 2e-5
        if sol.alt_m is not None:  # the GPGGA of epoch 7 says 3 m higher
            assert abs(sol.alt_m - ref.alt_m) < 3.01
        if sol.speed_m_s is not None:
            assert sol.speed_m_s == pytest.approx(ref.speed_m_s, abs=0.01)


# --- dual-antenna heading (HDT) -----------------------------------------------------------------

GST = "GPGST,123519.00,,,,,1.200,1.100,2.300"


def test_hdt_heading_travels_with_its_epoch_when_expected() -> None:
    # a dual-antenna receiver sends HDT after the timed sentences: expected, it completes the
    # epoch; not expected, it would be credited to the next one (the GPS_HDT parameter)
    data = s(GGA) + s(RMC) + s(GST) + s("GNHDT,271.25,T") + s(GGA2)
    sols, decoder = decode(data, expected_sentences=["GGA", "RMC", "GST", "HDT"])
    assert [sol.heading_deg for sol in sols] == [271.25, None]
    assert sols[0].sentences == ("GPGGA", "GPRMC", "GPGST", "GNHDT")
    assert decoder.counters.malformed == 0
    sols, _ = decode(data, expected_sentences=["GGA", "RMC", "GST"])
    assert [sol.heading_deg for sol in sols] == [None, 271.25]


def test_hdt_without_a_heading_solution_and_malformed_hdt() -> None:
    (sol,), decoder = decode(s(GGA) + s("GPHDT,,T"))
    assert sol.heading_deg is None and decoder.counters.malformed == 0
    (sol,), _ = decode(s(GGA) + s("GPHDT,360.00,T"))
    assert sol.heading_deg == 0.0
    for body in ("GPHDT,271.2,M", "GPHDT,371.0,T", "GPHDT,-1.0,T", "GPHDT,2x1,T", "GPHDT,nan,T"):
        out, decoder = decode(s(GGA) + s(body))
        assert decoder.counters.malformed == 1, body
        assert [sol.heading_deg for sol in out] == [None], body


def test_hdt_encodes_and_decodes_back() -> None:
    sol = GpsSolution(utc=45319.0, lat_deg=48.1, lon_deg=11.5, alt_m=500.0, fix=1, sats=9,
                      speed_m_s=20.0, course_deg=90.0, heading_deg=93.456)
    data = encode_epoch(sol, "GN", ("GGA", "RMC", "HDT"))
    assert data.endswith(s("GNHDT,93.46,T"))
    (back,), _ = decode(data, expected_sentences=["GGA", "RMC", "HDT"])
    assert back.heading_deg == pytest.approx(93.46) and back.course_deg == pytest.approx(90.0)
    without = encode_epoch(GpsSolution(utc=45319.0, fix=0), "GP", ("GGA", "HDT"))
    assert without.endswith(s("GPHDT,,T"))
    with pytest.raises(ValueError, match="heading_deg"):
        encode_epoch(GpsSolution(utc=45319.0, heading_deg=math.inf), "GP", ("HDT",))
