"""Keep docs/devices.md honest: its worked examples are the test vectors, and the decoders agree.

The page marks every checked block with an HTML comment ``<!-- check: NAME -->`` right before a
fenced code block or a Markdown table. Blocks hold hex bytes (``#`` starts a comment, a leading
``NNN:`` is an offset), ``key = value`` lines, Python code, or tables. Each test reads one or more
of them and compares them with tests/data/vectors/devices.json, tests/data/vectors/imu-cycle.bin,
the GPS capture and the project's decoders, so the page cannot drift from either.
"""

from __future__ import annotations

import json
import math
import re
import struct
from collections.abc import Callable
from functools import reduce
from operator import xor
from pathlib import Path
from typing import Any

import pytest
from conftest import data_file

from companion.drivers.gps import EXPECTED as DRIVER_EXPECTED_SENTENCES
from companion.drivers.gps_protocol import NmeaDecoder
from companion.drivers.gps_solution import GpsSolution
from companion.drivers.imu_protocol import (
    FAST_FRAME_LEN,
    SLOW_BLOCK_LEN,
    SYNC,
    ImuDecoder,
    ImuFast,
    ImuSlow,
    crc16_ccitt_false,
    decode_fast_frame,
    decode_slow_block,
    encode_fast_frame,
    encode_slow_block,
)
from companion.drivers.servo_protocol import (
    AUTO_SWITCH_THRESHOLD_US,
    COMMAND_LEN,
    COMMAND_SYNC,
    MAX_PLAUSIBLE_US,
    PILOT_LEN,
    PILOT_SYNC,
    PilotFrame,
    ServoCommand,
    decode_command,
    decode_pilot,
    encode_command,
    encode_pilot,
    pilot_switch_auto,
)

DOC = Path(__file__).resolve().parent.parent / "docs" / "devices.md"
ALL_SENTENCES = ("GGA", "RMC", "VTG", "GSA", "GST", "POS")
MARKER = re.compile(r"<!--\s*check:\s*([\w-]+)\s*-->")
RAW_COMMENT = re.compile(r"raw (0x[0-9A-Fa-f]+) = (-?\d+)")
STANDARD_GRAVITY_M_S2 = 9.80665
UNIT_TO_SI = {
    "deg/s": math.pi / 180.0,
    "rad/s": 1.0,
    "g": STANDARD_GRAVITY_M_S2,
    "m/s²": 1.0,
    "°C": 1.0,
    "us": 1.0,
}
TYPE_SIZES = {"uint8": 1, "int16": 2, "uint16": 2, "int32": 4}
TYPE_FORMATS = {"uint8": "<B", "int16": "<h", "uint16": "<H", "int32": "<i"}


# ---------------------------------------------------------------------------------------------
# Reading the page


def _doc_text() -> str:
    if not DOC.is_file():
        pytest.fail(f"{DOC} is missing", pytrace=False)
    return DOC.read_text(encoding="utf-8")


def _checked_blocks() -> dict[str, list[str]]:
    """Every ``<!-- check: NAME -->`` block of the page: the lines of its code block or table."""
    lines = _doc_text().splitlines()
    blocks: dict[str, list[str]] = {}
    for index, line in enumerate(lines):
        match = MARKER.fullmatch(line.strip())
        if match is None:
            continue
        name = match[1]
        assert name not in blocks, f"check block {name!r} appears twice in {DOC.name}"
        start = index + 1
        while start < len(lines) and not lines[start].strip():
            start += 1
        assert start < len(lines), f"check block {name!r} is followed by nothing"
        body: list[str] = []
        if lines[start].startswith("```"):
            end = start + 1
            while end < len(lines) and not lines[end].startswith("```"):
                body.append(lines[end])
                end += 1
            assert end < len(lines), f"code block of {name!r} is not closed"
        elif lines[start].startswith("|"):
            end = start
            while end < len(lines) and lines[end].startswith("|"):
                body.append(lines[end])
                end += 1
        else:
            pytest.fail(f"check block {name!r} is neither a code block nor a table")
        blocks[name] = body
    return blocks


def _block(name: str) -> list[str]:
    blocks = _checked_blocks()
    assert name in blocks, f"{DOC.name} has no block marked <!-- check: {name} -->"
    return blocks[name]


def _hex(name: str) -> bytes:
    out = bytearray()
    for line in _block(name):
        text = line.split("#", 1)[0]
        text = re.sub(r"^\s*\d+:", "", text)
        out += bytes.fromhex(text)
    return bytes(out)


def _key_values(name: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for line in _block(name):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        key, sep, value = text.partition("=")
        assert sep, f"{name}: line {line!r} is not 'key = value'"
        key = key.strip()
        assert key not in out, f"{name}: {key} stated twice"
        out[key] = value.strip()
    return out


def _comments(name: str) -> list[str]:
    return [line.split("#", 1)[1] for line in _block(name) if "#" in line]


def _cell(text: str) -> str:
    return text.strip().strip("`").strip()


def _table(name: str) -> list[dict[str, str]]:
    lines = _block(name)
    header = [_cell(c) for c in lines[0].strip().strip("|").split("|")]
    rows = []
    for line in lines[1:]:
        cells = [_cell(c) for c in line.strip().strip("|").split("|")]
        if all(set(c) <= set("-: ") for c in cells):
            continue  # the |---|---| separator
        assert len(cells) == len(header), f"{name}: row {line!r} has {len(cells)} cells"
        rows.append(dict(zip(header, cells, strict=True)))
    return rows


def _matches(stated: str, actual: Any) -> bool:
    """Whether a value printed on the page equals ``actual`` to the precision it is printed with."""
    if actual is None:
        return stated == "none"
    if isinstance(actual, bool):
        return stated == ("true" if actual else "false")
    if isinstance(actual, int):
        try:
            return int(stated, 0) == actual
        except ValueError:
            return False
    if isinstance(actual, float):
        try:
            value = float(stated)
        except ValueError:
            return False
        if "." in stated:
            decimals = len(stated.split(".", 1)[1])
            tolerance = 0.5 * 10.0**-decimals + 1e-12
        else:
            tolerance = 1e-9
        return abs(value - actual) <= tolerance
    return stated == str(actual)


def _check_stated(name: str, actual: dict[str, Any], *, exact_keys: bool = True) -> None:
    stated = _key_values(name)
    if exact_keys:
        assert set(stated) == set(actual), (
            f"{name}: the page states {sorted(stated)}, the test knows {sorted(actual)}"
        )
    for key, text in stated.items():
        assert key in actual, f"{name}: the page states {key}, which the test cannot check"
        assert _matches(text, actual[key]), f"{name}: page says {key} = {text}, got {actual[key]!r}"


def _check_raw_comments(name: str, example: bytes) -> None:
    """``raw 0xHHHH = N`` comments: N is the two's complement reading and its bytes are sent."""
    found = 0
    for comment in _comments(name):
        for match in RAW_COMMENT.finditer(comment):
            digits = match[1][2:]
            bits = 4 * len(digits)
            unsigned = int(digits, 16)
            signed = unsigned - (1 << bits) if unsigned >= 1 << (bits - 1) else unsigned
            assert signed == int(match[2]), f"{name}: {match[0]} (reads as {signed})"
            assert unsigned.to_bytes(bits // 8, "little") in example, (
                f"{name}: {match[0]} is not in the example bytes"
            )
            found += 1
    assert found, f"{name}: no 'raw 0x... = N' comment found"


def _vectors() -> dict[str, Any]:
    data: dict[str, Any] = json.loads(data_file("vectors", "devices.json").read_text())
    return data


def _capture_lines() -> set[str]:
    raw = data_file("gps_gn_ashtech_capture.nmea").read_bytes()
    return {line.lstrip(b"\x00").decode("latin-1") for line in raw.split(b"\r\n")}


# ---------------------------------------------------------------------------------------------
# Decoded values, named as on the page


def _motion(decoded: ImuFast | ImuSlow, rate: str = "", accel: str = "") -> dict[str, Any]:
    """Rates and accelerations under the page's names (`rate`/`accel`: their unit suffixes)."""
    names = ("p", "q", "r", "ax", "ay", "az")
    values = (*decoded.rates_rad_s, *decoded.accel_m_s2)
    suffixes = (rate,) * 3 + (accel,) * 3
    return {n + s: v for n, s, v in zip(names, suffixes, values, strict=True)}


def _fast_values(frame: bytes, fast: ImuFast) -> dict[str, Any]:
    return {"counter": fast.counter, "status": fast.status, **_motion(fast, "_rad_s", "_m_s2"),
            "slow_word": fast.slow_word, "checksum": struct.unpack_from("<H", frame, 18)[0]}


def _slow_values(block: bytes, slow: ImuSlow) -> dict[str, Any]:
    return {**_motion(slow, "_rad_s", "_m_s2"), "temperature_c": slow.temperature_c,
            "bit_word": slow.bit_word, "crc": struct.unpack_from("<H", block, 198)[0]}


def _servo_values(frame: bytes, decoded: ServoCommand | PilotFrame) -> dict[str, Any]:
    out: dict[str, Any] = {"seq": decoded.seq, "checksum": frame[-1]}
    out.update({f"ch{i + 1}_us": us for i, us in enumerate(decoded.channels_us)})
    if isinstance(decoded, ServoCommand):
        out["auto_requested"] = decoded.auto_requested
    else:
        out.update(
            auto_engaged=decoded.auto_engaged,
            failsafe=decoded.failsafe,
            avionics_batt_raw=decoded.avionics_batt_raw,
            servo_batt_raw=decoded.servo_batt_raw,
        )
    return out


def _gps_values(sol: GpsSolution) -> dict[str, Any]:
    names = (
        "lat_deg",
        "lon_deg",
        "alt_m",
        "geoid_sep_m",
        "alt_ellipsoid_m",
        "fix",
        "sats",
        "hdop",
        "pdop",
        "vdop",
        "tdop",
        "speed_m_s",
        "course_deg",
        "vn_m_s",
        "ve_m_s",
        "vd_m_s",
        "alt_std_m",
        "lat_std_m",
        "lon_std_m",
    )
    out: dict[str, Any] = {name: getattr(sol, name) for name in names}
    out["utc_s"] = sol.utc
    out["date"] = None if sol.date is None else sol.date.isoformat()
    return out


# ---------------------------------------------------------------------------------------------
# The page as a whole


def test_every_example_the_tests_rely_on_is_marked() -> None:
    wanted = {
        "imu-layout-fast",
        "imu-fast-hex",
        "imu-fast-decoded",
        "imu-fast-checksum",
        "imu-layout-slow",
        "imu-slow-hex",
        "imu-slow-decoded",
        "imu-slow-words",
        "crc-check",
        "imu-cycle-start",
        "imu-cycle-result",
        "nmea-checksum-steps",
        "gps-fields-GGA",
        "gps-fields-RMC",
        "gps-fields-VTG",
        "gps-fields-GSA",
        "gps-fields-GST",
        "gps-fields-POS",
        "gps-epoch",
        "gps-epoch-decoded",
        "gps-epoch-no-pos",
        "gps-capture-result",
        "servo-layout-command",
        "servo-layout-pilot",
        "servo-command-hex",
        "servo-command-decoded",
        "servo-command-checksum",
        "servo-pilot-hex",
        "servo-pilot-decoded",
        "servo-pilot-checksum",
        "checksum-code",
    }
    assert set(_checked_blocks()) == wanted


@pytest.mark.parametrize(
    ("block", "key"),
    [
        ("imu-fast-hex", "fast_frame_0_hex"),
        ("imu-slow-hex", "slow_block_hex"),
        ("servo-command-hex", "servo_command_hex"),
        ("servo-pilot-hex", "servo_pilot_hex"),
    ],
)
def test_hex_examples_are_the_vectors(block: str, key: str) -> None:
    assert _hex(block) == bytes.fromhex(_vectors()[key])


# ---------------------------------------------------------------------------------------------
# IMU


def test_imu_fast_example_decodes_to_the_stated_values() -> None:
    frame = _hex("imu-fast-hex")
    values = _fast_values(frame, decode_fast_frame(frame))
    _check_stated("imu-fast-decoded", values)
    _check_raw_comments("imu-fast-decoded", frame)
    stated = _key_values("imu-fast-decoded")
    expected = _vectors()["fast_values_quantised"]
    assert _matches(stated["status"], expected["status"])
    for i, axis in enumerate("pqr"):
        assert _matches(stated[f"{axis}_rad_s"], float(expected["rates_rad_s"][i]))
    for i, axis in enumerate(("ax", "ay", "az")):
        assert _matches(stated[f"{axis}_m_s2"], float(expected["specific_force_m_s2"][i]))


def test_imu_slow_example_decodes_to_the_stated_values() -> None:
    block = _hex("imu-slow-hex")
    values = _slow_values(block, decode_slow_block(block))
    _check_stated("imu-slow-decoded", values)
    _check_raw_comments("imu-slow-decoded", block)
    stated = _key_values("imu-slow-decoded")
    assert int(stated["crc"], 0) == crc16_ccitt_false(block[:198])
    expected = _vectors()["slow_values"]
    for i, axis in enumerate("pqr"):
        assert _matches(stated[f"{axis}_rad_s"], float(expected["rates_rad_s"][i]))
    for i, axis in enumerate(("ax", "ay", "az")):
        assert _matches(stated[f"{axis}_m_s2"], float(expected["specific_force_m_s2"][i]))
    assert _matches(stated["temperature_c"], float(expected["temperature_c"]))
    assert _matches(stated["bit_word"], expected["bit"])


def test_crc_check_value() -> None:
    assert int(_key_values("crc-check")["crc_123456789"], 0) == crc16_ccitt_false(b"123456789")


def test_slow_words_table_matches_the_cycle_file() -> None:
    stream = data_file("vectors", "imu-cycle.bin").read_bytes()
    frames = [item for item in ImuDecoder().feed(stream, 0) if isinstance(item, ImuFast)]
    by_counter = {frame.counter: frame.slow_word.to_bytes(2, "little") for frame in frames}
    block = bytes.fromhex(_vectors()["slow_block_hex"])
    covered: set[int] = set()
    for row in _table("imu-slow-words"):
        first, _, last = row["counter"].partition("..")
        counters = range(int(first), int(last or first) + 1)
        word = bytes.fromhex(row["frame bytes 16, 17"])
        for counter in counters:
            assert by_counter[counter] == word, f"counter {counter}"
            assert block[2 * counter : 2 * counter + 2] == word, f"counter {counter}"
            covered.add(counter)
        offsets = [int(x) for x in re.split(r"\.\.|,", row["block offsets"])]
        assert offsets == [2 * counters[0], 2 * counters[-1] + 1]
    assert covered == set(range(100))


def test_cycle_file_start_and_result() -> None:
    stream = data_file("vectors", "imu-cycle.bin").read_bytes()
    head = _hex("imu-cycle-start")
    assert stream.startswith(head)
    frame0 = head[-FAST_FRAME_LEN:]
    example = bytes.fromhex(_vectors()["fast_frame_0_hex"])
    assert frame0[:16] == example[:16] and frame0[16:] != example[16:]
    assert "0x0623" in _doc_text() and struct.unpack_from("<H", frame0, 18)[0] == 0x0623

    stated = _key_values("imu-cycle-result")
    whole = ImuDecoder()
    by_byte = ImuDecoder()
    results = [whole.feed(stream, 0)]
    results.append(
        [item for i in range(len(stream)) for item in by_byte.feed(stream[i : i + 1], i)]
    )
    for decoder, items in zip((whole, by_byte), results, strict=True):
        actual = {
            "file_bytes": len(stream),
            "bytes_discarded": decoder.counters.bytes_discarded,
            "bad_checksum": decoder.counters.bad_checksum,
            "fast_frames": sum(isinstance(item, ImuFast) for item in items),
            "slow_blocks": sum(isinstance(item, ImuSlow) for item in items),
        }
        _check_stated("imu-cycle-result", actual)
        assert int(stated["slow_blocks"]) == decoder.counters.slow_good


# ---------------------------------------------------------------------------------------------
# Layout tables


def _checksum_of(name: str, frame: bytes) -> int:
    if name == "imu-layout-fast":
        return sum(frame[2:18]) & 0xFFFF
    if name == "imu-layout-slow":
        return crc16_ccitt_false(frame[:198])
    return reduce(xor, frame[2:-1], 0)


def _layout_fields(name: str, frame: bytes) -> dict[str, Any]:
    """What the project's decoder reads from ``frame``, under the field names of the table."""
    if name == "imu-layout-fast":
        fast = decode_fast_frame(frame)
        return {"counter": fast.counter, "status": fast.status, **_motion(fast),
                "slow_word": fast.slow_word}
    if name == "imu-layout-slow":
        slow = decode_slow_block(frame)
        return {**_motion(slow), "temperature": slow.temperature_c, "bit_word": slow.bit_word}
    decoded: ServoCommand | PilotFrame
    if name == "servo-layout-command":
        decoded = decode_command(frame)
        out: dict[str, Any] = {"flags": int(decoded.auto_requested)}
    else:
        decoded = decode_pilot(frame)
        out = {
            "flags": int(decoded.auto_engaged) | int(decoded.failsafe) << 1,
            "avionics_batt": decoded.avionics_batt_raw,
            "servo_batt": decoded.servo_batt_raw,
        }
    out["seq"] = decoded.seq
    out.update({f"ch{i + 1}": us for i, us in enumerate(decoded.channels_us)})
    return out


LAYOUTS: dict[str, tuple[str, int, bytes]] = {
    "imu-layout-fast": ("imu-fast-hex", FAST_FRAME_LEN, SYNC),
    "imu-layout-slow": ("imu-slow-hex", SLOW_BLOCK_LEN, b""),
    "servo-layout-command": ("servo-command-hex", COMMAND_LEN, COMMAND_SYNC),
    "servo-layout-pilot": ("servo-pilot-hex", PILOT_LEN, PILOT_SYNC),
}


def _busy_frame(name: str) -> bytes:
    """A frame from the project's encoder with every field non-zero and distinct, so that a wrong
    LSB or offset in a table cannot hide behind a zero in the vector."""
    if name == "imu-layout-fast":
        return encode_fast_frame(57, 0x05, (0.1, -0.2, 0.3), (1.5, -2.5, -9.0), 0xBEEF)
    if name == "imu-layout-slow":
        return encode_slow_block((0.01, -0.02, 0.03), (0.4, -0.5, -9.7), -12.34, 0x8102)
    channels = (1000, 1100, 1200, 1300, 1800, 1900, 1950, 2000)
    if name == "servo-layout-command":
        return encode_command(ServoCommand(200, True, channels))
    return encode_pilot(PilotFrame(201, True, True, channels, 200, 142))


@pytest.mark.parametrize("frame_source", ["vector", "encoder"])
@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_layout_table_reads_frames_as_the_decoder_does(name: str, frame_source: str) -> None:
    example_block, length, sync = LAYOUTS[name]
    frame = _hex(example_block) if frame_source == "vector" else _busy_frame(name)
    fields = _layout_fields(name, frame)
    seen: set[str] = set()
    offset = 0
    for row in _table(name):
        where = f"{name}, field {row['field']}"
        assert int(row["offset"]) == offset, f"{where}: offset {row['offset']}, expected {offset}"
        size = int(row["size"])
        offset += size
        field = row["field"]
        if row["type"] == "bytes":
            assert field == "padding" and not any(frame[offset - size : offset]), where
            continue
        assert TYPE_SIZES[row["type"]] == size, f"{where}: {row['type']} is not {size} bytes"
        assert row["order"] == ("LE" if size > 1 else "-"), f"{where}: byte order {row['order']}"
        (raw,) = struct.unpack_from(TYPE_FORMATS[row["type"]], frame, offset - size)
        if field.startswith("sync"):
            stated = re.search(r"0x([0-9A-Fa-f]{2})", row["meaning"])
            assert stated is not None, f"{where}: no sync value"
            index = int(field[-1]) - 1
            assert raw == int(stated[1], 16) == sync[index], where
        elif field in ("checksum", "crc"):
            assert raw == _checksum_of(name, frame), where
        else:
            assert field in fields, f"{where}: the test does not know this field"
            seen.add(field)
            lsb = re.match(r"([-+0-9.eE]+)\s+(\S+)", row["LSB"])
            if lsb is None:
                assert raw == fields[field], f"{where}: raw {raw}, decoder {fields[field]}"
                continue
            lsb_si = float(lsb[1]) * UNIT_TO_SI[lsb[2]]
            assert math.isclose(raw * lsb_si, fields[field], rel_tol=1e-9, abs_tol=1e-12), where
            in_si = re.search(r"\(([-+0-9.eE]+)\s+(\S+)\)", row["LSB"])
            if in_si is not None:
                assert UNIT_TO_SI[in_si[2]] == 1.0, where
                assert math.isclose(float(in_si[1]), lsb_si, rel_tol=1e-7), where
    assert offset == length, f"{name}: fields add up to {offset} bytes, the frame has {length}"
    assert seen == set(fields), f"{name}: fields missing from the table: {set(fields) - seen}"


# ---------------------------------------------------------------------------------------------
# Checksums


@pytest.mark.parametrize(
    ("name", "example", "start", "stop", "key"),
    [
        ("imu-fast-checksum", "imu-fast-hex", 2, 18, "sum"),
        ("servo-command-checksum", "servo-command-hex", 2, 20, "xor"),
        ("servo-pilot-checksum", "servo-pilot-hex", 2, 22, "xor"),
    ],
)
def test_checksum_worked_examples(name: str, example: str, start: int, stop: int, key: str) -> None:
    frame = _hex(example)
    stated = _key_values(name)
    assert set(stated) == {"covered", key}
    covered = bytes.fromhex(stated["covered"])
    assert covered == frame[start:stop]
    if key == "sum":
        result = sum(covered) & 0xFFFF
        assert frame[stop:] == result.to_bytes(2, "little")
    else:
        result = reduce(xor, covered, 0)
        assert frame[stop:] == bytes([result])
    assert int(stated[key], 0) == result


def test_reference_code_agrees_with_the_decoders() -> None:
    code = "\n".join(_block("checksum-code"))
    namespace: dict[str, Any] = {}
    exec(compile(code, str(DOC), "exec"), namespace)
    fast_sum: Callable[[bytes], int] = namespace["imu_fast_checksum"]
    crc: Callable[[bytes], int] = namespace["crc16_ccitt_false"]
    servo_sum: Callable[[bytes], int] = namespace["servo_checksum"]
    nmea_sum: Callable[[str], int] = namespace["nmea_checksum"]
    vectors = _vectors()

    frame = bytes.fromhex(vectors["fast_frame_0_hex"])
    assert fast_sum(frame) == struct.unpack_from("<H", frame, 18)[0]
    decode_fast_frame(frame)  # the project's decoder accepts the same checksum
    block = bytes.fromhex(vectors["slow_block_hex"])
    stored_crc = struct.unpack_from("<H", block, 198)[0]
    assert crc(block[:198]) == crc16_ccitt_false(block[:198]) == stored_crc
    assert crc(b"123456789") == crc16_ccitt_false(b"123456789")
    for key, decode in (("servo_command_hex", decode_command), ("servo_pilot_hex", decode_pilot)):
        servo_frame = bytes.fromhex(vectors[key])
        assert servo_sum(servo_frame) == servo_frame[-1]
        decode(servo_frame)
    checked = 0
    for line in _capture_lines():
        match = re.fullmatch(r"\$+([\x20-\x7e]*)\*([0-9A-F]{2})", line)
        if match is not None and "$" not in match[1]:
            assert nmea_sum(line) == int(match[2], 16), line
            checked += 1
    assert checked > 50


# ---------------------------------------------------------------------------------------------
# GPS


def test_nmea_checksum_steps() -> None:
    rows = _table("nmea-checksum-steps")
    body = "".join(row["character"] for row in rows)
    running = 0
    for row in rows:
        assert int(row["code"], 16) == ord(row["character"])
        running ^= ord(row["character"])
        assert int(row["XOR so far"], 16) == running, row
    sentence = f"${body}*{running:02X}"
    assert sentence in _capture_lines()
    assert f"`{sentence}`" in _doc_text()


def _epoch_lines() -> list[str]:
    return [line.strip() for line in _block("gps-epoch") if line.strip()]


def test_gps_examples_are_lines_of_the_capture() -> None:
    capture = _capture_lines()
    for line in _epoch_lines():
        assert line in capture, line
    inline = re.findall(r"Example\s+`(\$[^`]+)`", _doc_text())
    assert len(inline) == 6
    for sentence in inline:
        assert sentence in _epoch_lines(), sentence


@pytest.mark.parametrize("kind", ALL_SENTENCES)
def test_gps_field_table_numbers_the_fields_of_the_example(kind: str) -> None:
    prefix = "$PASHR,POS," if kind == "POS" else f"$GN{kind},"
    sentence = next(line for line in _epoch_lines() if line.startswith(prefix))
    fields = sentence[1:].split("*", 1)[0].split(",")
    covered: set[int] = set()
    for row in _table(f"gps-fields-{kind}"):
        first, _, last = row["field"].partition("..")
        numbers = range(int(first), int(last or first) + 1)
        covered.update(numbers)
        if not last:
            assert fields[numbers[0]] == row["example"], f"{kind} field {row['field']}"
        else:
            first_example = row["example"].split()[0].strip("`")
            assert first_example == fields[numbers[0]], f"{kind} field {row['field']}"
    assert covered == set(range(1, len(fields))), f"{kind}: fields left out of the table"


def _decode_epoch(lines: list[str], expected: tuple[str, ...]) -> GpsSolution:
    decoder = NmeaDecoder(expected_sentences=expected)
    data = "".join(f"{line}\r\n" for line in lines).encode("ascii")
    solutions = decoder.feed(data, 0) + decoder.flush(0)
    assert len(solutions) == 1
    return solutions[0]


def test_gps_epoch_example_decodes_to_the_stated_values() -> None:
    solution = _decode_epoch(_epoch_lines(), ALL_SENTENCES)
    _check_stated("gps-epoch-decoded", _gps_values(solution))


def test_gps_epoch_without_pashr_pos() -> None:
    lines = [line for line in _epoch_lines() if not line.startswith("$PASHR,POS")]
    solution = _decode_epoch(lines, ALL_SENTENCES[:-1])
    values = _gps_values(solution)
    _check_stated("gps-epoch-no-pos", values, exact_keys=False)
    changed = set(_key_values("gps-epoch-no-pos"))
    assert changed == {"vd_m_s", "tdop", "alt_ellipsoid_m"}
    full = _key_values("gps-epoch-decoded")
    for key, text in full.items():
        if key not in changed:
            assert _matches(text, values[key]), f"without PASHR,POS {key} = {values[key]!r}"


def test_gps_capture_result() -> None:
    capture = data_file("gps_gn_ashtech_capture.nmea").read_bytes()
    decoder = NmeaDecoder(expected_sentences=ALL_SENTENCES)
    solutions = decoder.feed(capture, 0) + decoder.flush(0)
    default = NmeaDecoder(expected_sentences=DRIVER_EXPECTED_SENTENCES)
    default_solutions = default.feed(capture, 0) + default.flush(0)
    at_30_70 = [s for s in solutions if s.utc is not None and round(s.utc * 100) == 3693070]
    assert len(at_30_70) == 1
    actual = {
        "epochs": len(solutions),
        "first_utc_s": solutions[0].utc,
        "last_utc_s": solutions[-1].utc,
        "epochs_with_vd": sum(s.vd_m_s is not None for s in solutions),
        "epochs_with_vd_default": sum(s.vd_m_s is not None for s in default_solutions),
        "lat_deg_at_36930_70": at_30_70[0].lat_deg,
    }
    _check_stated("gps-capture-result", actual)
    assert len(default_solutions) == len(solutions)


# ---------------------------------------------------------------------------------------------
# Servo board


@pytest.mark.parametrize("direction", ["command", "pilot"])
def test_servo_examples_decode_to_the_stated_values(direction: str) -> None:
    frame = _hex(f"servo-{direction}-hex")
    decoded: ServoCommand | PilotFrame
    decoded = decode_command(frame) if direction == "command" else decode_pilot(frame)
    name = f"servo-{direction}-decoded"
    _check_stated(name, _servo_values(frame, decoded))
    stated = _key_values(name)
    expected = _vectors()[f"servo_{direction}"]
    renames = {"battery_logic": "avionics_batt_raw", "battery_servo": "servo_batt_raw"}
    for key, value in expected.items():
        if key == "channels_us":
            for i, us in enumerate(value):
                assert _matches(stated[f"ch{i + 1}_us"], us)
        else:
            assert _matches(stated[renames.get(key, key)], value), key


def test_switch_threshold_and_pulse_limit_on_the_page_are_the_code_s() -> None:
    text = _doc_text()
    thresholds = re.findall(r"above (\d+) us", text)
    assert thresholds and {int(t) for t in thresholds} == {AUTO_SWITCH_THRESHOLD_US}
    assert f"strictly above {AUTO_SWITCH_THRESHOLD_US} us" in text
    limits = re.findall(r"(?:at most|exceeds|up to) (\d+) us", text)
    assert limits and {int(t) for t in limits} == {MAX_PLAUSIBLE_US}
    channels = [1500] * 8
    channels[4] = AUTO_SWITCH_THRESHOLD_US
    assert not pilot_switch_auto(channels)
    channels[4] = AUTO_SWITCH_THRESHOLD_US + 1
    assert pilot_switch_auto(channels)
