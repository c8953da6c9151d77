"""The format pages (docs/logs.md, docs/legacy-protocol.md) against the code and the test vectors.

The pages claim to be complete enough to write a decoder from: their tables (record types,
conversions, message types, field layouts, header) and their worked examples (hex dumps, decoded
values, CSV lines) are parsed here and compared with the project's codecs and with the vector
files, so a page that drifts from the code fails a test.
"""

from __future__ import annotations

import json
import re
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import data_file

from companion.logs import records
from companion.logs.convert import convert_file
from companion.logs.formats import FormatError, parse_format
from companion.logs.framing import framed_length
from companion.logs.reader import read_log_bytes
from legacy_protocol import codec, messages

REPO = Path(__file__).resolve().parent.parent
DOCS = REPO / "docs"

Table = tuple[list[str], list[list[str]]]


# -- reading the markdown --------------------------------------------------------------------


def _doc(name: str) -> str:
    path = DOCS / name
    if not path.is_file():
        pytest.fail(f"docs/{name} is missing", pytrace=False)
    return path.read_text(encoding="utf-8")


def _is_fence(line: str) -> bool:
    return line.lstrip().startswith("```")


def _section(text: str, title: str) -> str:
    """Text under the heading `title` (e.g. ``## Worked example``) up to the next heading of the
    same or a higher level, code blocks excluded from the heading search."""
    lines = text.splitlines()
    level = len(title) - len(title.lstrip("#"))
    try:
        start = next(i for i, line in enumerate(lines) if line.strip() == title)
    except StopIteration:
        pytest.fail(f"heading {title!r} not found", pytrace=False)
    out: list[str] = []
    fenced = False
    for line in lines[start + 1 :]:
        if _is_fence(line):
            fenced = not fenced
        elif not fenced and re.match(rf"#{{1,{level}}} ", line):
            break
        out.append(line)
    return "\n".join(out)


def _subsections(text: str, level: int) -> list[tuple[str, str]]:
    """(heading text, body) of every heading of exactly `level` in `text`."""
    out: list[tuple[str, list[str]]] = []
    fenced = False
    for line in text.splitlines():
        if _is_fence(line):
            fenced = not fenced
        m = None if fenced else re.match(rf"(#{{1,{level}}}) (.*)$", line)
        if m is not None:
            if len(m.group(1)) == level:
                out.append((m.group(2).strip(), []))
                continue
            break
        if out:
            out[-1][1].append(line)
    return [(title, "\n".join(body)) for title, body in out]


def _tables(text: str) -> list[Table]:
    """Every markdown table of `text`: (header cells, rows of cells), separator row dropped."""
    tables: list[Table] = []
    block: list[list[str]] = []
    for line in [*text.splitlines(), ""]:
        if line.startswith("|"):
            block.append([c.strip() for c in line.strip().strip("|").split("|")])
            continue
        if block:
            assert len(block) >= 2 and set("".join(block[1])) <= set("-: "), block
            tables.append((block[0], block[2:]))
            block = []
    return tables


def _table(text: str, first_header: str) -> list[list[str]]:
    """Rows of the one table of `text` whose first header cell is `first_header`."""
    found = [rows for header, rows in _tables(text) if header[0] == first_header]
    assert len(found) == 1, f"expected one table starting with {first_header!r}, got {len(found)}"
    return found[0]


def _code_blocks(text: str) -> list[tuple[str, list[str]]]:
    """(info string, lines) of every fenced code block of `text`."""
    out: list[tuple[str, list[str]]] = []
    current: list[str] | None = None
    info = ""
    for line in text.splitlines():
        if _is_fence(line):
            if current is None:
                info, current = line.strip()[3:].strip(), []
            else:
                out.append((info, current))
                current = None
        elif current is not None:
            current.append(line)
    return out


def _hex(*cells: str) -> bytes:
    """The bytes written as backquoted hex in table cells (`db 04 10 00`)."""
    groups = [g for cell in cells for g in re.findall(r"`([0-9a-fA-F ]*)`", cell)]
    return bytes.fromhex(" ".join(groups))


def _ticked(cell: str) -> str:
    m = re.fullmatch(r"`([^`]+)`", cell.strip())
    assert m is not None, f"expected one backquoted name, got {cell!r}"
    return m.group(1)


_NUMBER = re.compile(r"-?0x[0-9A-Fa-f]+|-?\d+\.\d+(?:[eE][-+]?\d+)?|-?\d+")


def _number(cell: str) -> int | float:
    """The number a table cell starts with: decimal, hexadecimal (0x...) or decimal fraction."""
    m = _NUMBER.match(cell.strip())
    assert m is not None, f"no number at the start of {cell!r}"
    text = m.group(0)
    if "x" in text:
        return int(text, 16)
    return float(text) if "." in text else int(text)


def _f32(x: float) -> float:
    value: float = struct.unpack("<f", struct.pack("<f", x))[0]
    return value


# -- docs/logs.md ------------------------------------------------------------------------------

LOG_VECTOR = "log-example.bin"
_DTYPES = {
    "int8": "<i1",
    "uint8": "<u1",
    "int16": "<i2",
    "uint16": "<u2",
    "int32": "<i4",
    "uint32": "<u4",
    "int64": "<i8",
    "uint64": "<u8",
    "float32": "<f4",
    "float64": "<f8",
}
_STRUCT_OF = {"uint8": "B", "uint16": "H", "int32": "i", "uint32": "I", "float32": "f"}


def _log_bytes() -> bytes:
    return data_file("vectors", LOG_VECTOR).read_bytes()


def _record_size(buf: bytes, offset: int) -> int:
    rtype = buf[offset]
    length = int.from_bytes(buf[offset + 2 : offset + 4], "little")
    timed = rtype in (records.BEGIN, records.END, records.DATA, records.ARRAY, records.ARRAY_ALT)
    return (records.TIMED_SIZE if timed else records.HEADER_SIZE) + length


def test_log_record_types_table_matches_the_codec() -> None:
    rows = _table(_section(_doc("logs.md"), "### Record header"), "type byte")
    seen: set[int] = set()
    for code_cell, name, index_cell, length_cell, body, total in rows:
        code = int(_ticked(code_cell), 16)
        seen.add(code)
        assert records.TYPE_NAMES.get(code) == name, (code_cell, name)
        m = re.fullmatch(r"(\d+)( \+ N)?", total)
        assert m is not None, total
        fixed, variable = int(m.group(1)), m.group(2) is not None
        timed = body.startswith("TIME")
        assert fixed == (records.TIMED_SIZE if timed else records.HEADER_SIZE), (name, total)
        n = 5 if variable else 0
        if not variable:
            assert index_cell == length_cell == "0", name
        # The reader frames a record of this type with the size the page gives.
        record = records.HEADER.pack(code, 0 if not variable else 1, n) + bytes(fixed + n - 4)
        definition = records.encode_definition(1, "%c%c%c%c%c")
        assert framed_length(definition + record + b"\xff") == len(definition) + fixed + n, name
        # ... and the writer's encoders produce it with that size.
        t_ns = 1_700_000_000 * 10**9
        if code in (records.BEGIN, records.END):
            assert len(records.encode_marker(code, t_ns)) == fixed + n
        elif code == records.COMMENT:
            assert len(records.encode_comment(1, "a,b,c")) == fixed + n
        elif code == records.DEFINITION:
            assert len(records.encode_definition(1, "%d %d")) == fixed + n
        elif code == records.DATA:
            packer = records.DataPacker(1, parse_format("%d%hhu"))
            assert len(packer.pack(t_ns, [1, 2])) == fixed + n
        elif code == records.ARRAY:
            assert len(records.encode_array(1, b"12345", t_ns)) == fixed + n
        else:  # 0xDA has no encoder: the reader must take it as a Byte Array
            lf = read_log_bytes(records.encode_definition(1, "%hhu") + record)
            assert [s.kind for s in lf.streams] == ["array"] and lf.data(1).size == n
    assert seen == set(records.KNOWN_TYPES)


def test_log_conversion_table_matches_the_format_parser() -> None:
    rows = _table(_section(_doc("logs.md"), "## Format strings"), "field type")
    documented: set[str] = set()
    for type_cell, size_cell, conversions in rows:
        dtype = np.dtype(_DTYPES[type_cell.split()[0]])
        assert int(size_cell) == dtype.itemsize, type_cell
        specs = re.findall(r"`(%[^`]+)`", conversions)
        assert specs, type_cell
        for spec in specs:
            parsed = parse_format(spec)
            assert [c.dtype for c in parsed.conversions] == [dtype], spec
            assert parsed.size == dtype.itemsize, spec
            documented.add(spec)
    # Every conversion the parser accepts is in the table, and nothing else.
    accepted: set[str] = set()
    for length in ("", "hh", "h", "l", "ll", "L", "j", "z", "t"):
        for letter in "diouxXcfFeEgGaAspn":
            spec = f"%{length}{letter}"
            try:
                parse_format(spec)
            except FormatError:
                continue
            accepted.add(spec)
    assert accepted == documented


def _example_records(section: str) -> list[tuple[int, bytes, str]]:
    """(offset, record bytes, meaning) of every row of the worked example's record tables."""
    out: list[tuple[int, bytes, str]] = []
    for header, rows in _tables(section):
        if header[:2] != ["offset", "header"]:
            continue
        assert header == ["offset", "header", "TIME", "body", "meaning"], header
        for offset_cell, head, time, body, meaning in rows:
            out.append((int(offset_cell), _hex(head, time, body), meaning))
    return out


def test_log_example_hex_is_the_vector_file() -> None:
    buf = _log_bytes()
    section = _section(_doc("logs.md"), "## Worked example")
    rows = _example_records(section)
    assert len(rows) >= 10
    for offset, record, meaning in rows:
        assert buf[offset : offset + len(record)] == record, f"record at offset {offset}"
        assert len(record) == _record_size(buf, offset), f"record at offset {offset} is partial"
        assert records.TYPE_NAMES[record[0]] in meaning, (offset, meaning)
    # The first table shows the file's first records, back to back from byte 0.
    first = [r for r in rows if r[0] < 1000]
    assert first[0][0] == 0
    for (off, rec, _), (nxt, _, _) in zip(first, first[1:], strict=False):
        assert off + len(rec) == nxt, f"gap after the record at offset {off}"
    prefix = b"".join(rec for _, rec, _ in first)
    lf = read_log_bytes(prefix, name="doc example")
    assert not lf.damage and not lf.truncated_bytes
    assert lf.record_count == len(first)


def test_log_example_field_breakdown_decodes_as_shown() -> None:
    buf = _log_bytes()
    section = _section(_doc("logs.md"), "## Worked example")
    m = re.search(r"The Data Block at offset (\d+)", section)
    assert m is not None
    base = int(m.group(1))
    assert buf[base] == records.DATA
    rows = _table(section, "record offset")
    # The first rows are the timed header, the others the fields of the format's conversions.
    header_codes = list(records.TIMED_HEADER.format.lstrip("<"))
    assert [_STRUCT_OF[r[2]] for r in rows[: len(header_codes)]] == header_codes
    covered = 0
    for offset_cell, bytes_cell, type_cell, field, value_cell in rows:
        offset = int(offset_cell)
        raw = _hex(bytes_cell)
        assert offset == covered, f"row at record offset {offset} leaves a gap"
        covered = offset + len(raw)
        assert buf[base + offset : base + covered] == raw, f"bytes at record offset {offset}"
        value = struct.unpack("<" + _STRUCT_OF[type_cell], raw)[0]
        spec = re.search(r"\(`(%[^`]+)`\)", field)
        if spec is not None:
            conversion = parse_format(spec.group(1)).conversions[0]
            assert conversion.struct_code == _STRUCT_OF[type_cell], field
        assert value == _number(value_cell), (field, value_cell)
        printed = re.search(r"printed `([^`]*)`", value_cell)
        if printed is not None:
            assert spec is not None, field
            assert conversion.render(value) == printed.group(1), field
    assert covered == _record_size(buf, base)


def test_log_example_csv_is_what_the_converter_writes(tmp_path: Path) -> None:
    vector = data_file("vectors", LOG_VECTOR)
    outputs = {p.name: p.read_text(encoding="latin-1").splitlines() for p in
               convert_file(vector, tmp_path)}
    section = _section(_doc("logs.md"), "## Worked example")
    # Each csv block belongs to the CSV file named last before it in the text.
    blocks: list[tuple[str, list[str]]] = []
    named = ""
    fenced = False
    lines: list[str] = []
    for line in section.splitlines():
        if _is_fence(line):
            if not fenced and line.strip() == "```csv":
                lines = []
            elif fenced and lines:
                blocks.append((named, lines))
            fenced = not fenced
            continue
        if fenced:
            lines.append(line)
        else:
            names = re.findall(r"`(log-example_fmt\d+\.csv)`", line)
            named = names[-1] if names else named
    assert len(blocks) >= 2
    for name, block in blocks:
        assert name in outputs, f"csv block names {name!r}"
        produced = outputs[name]
        starts = [i for i in range(len(produced)) if produced[i : i + len(block)] == block]
        assert starts, f"csv block is not a run of lines of {name}:\n" + "\n".join(block)
        expected = data_file("vectors", name).read_text(encoding="latin-1").splitlines()
        data = [line for line in block if not line.startswith("%")]
        assert all(line in expected for line in data), f"data lines not in vectors/{name}"


# -- docs/legacy-protocol.md ----------------------------------------------------------------------

_WIRE_TYPES = {"B": "uint8", "H": "uint16", "I": "uint32", "i": "int32", "f": "float32",
               "d": "float64"}
_TYPE_SIZES = {"uint8": 1, "uint16": 2, "uint32": 4, "int32": 4, "float32": 4, "float64": 8,
               "char": 1}
_HEADER_CODES = {"uint8": "B", "uint16": "H", "uint32": "I", "int32": "i"}


def _type_size(text: str) -> int:
    m = re.fullmatch(r"(\w+)(?:\[(\d+)\])?", text)
    assert m is not None and m.group(1) in _TYPE_SIZES, text
    return _TYPE_SIZES[m.group(1)] * int(m.group(2) or 1)


def _wire_type(wire: messages.WireField) -> str:
    if wire.code.endswith("s"):
        return f"char[{wire.code[:-1]}]"
    base = _WIRE_TYPES[wire.code]
    return base if wire.count == 1 else f"{base}[{wire.count}]"


def _vectors() -> list[dict[str, Any]]:
    vectors: list[dict[str, Any]] = json.loads(
        data_file("vectors", "legacy-udp.json").read_text(encoding="utf-8")
    )
    return vectors


def test_legacy_type_table_matches_the_codec() -> None:
    rows = _table(_section(_doc("legacy-protocol.md"), "## Message types"), "code")
    seen: set[int] = set()
    for code_cell, name, direction, total, body in rows:
        code = int(_ticked(code_cell), 16)
        seen.add(code)
        assert codec.layout_of(code) == (name, int(total)), code_cell
        assert int(body) == int(total) - codec.HEADER_SIZE, name
        expected = "aircraft → ground" if code in messages.MESSAGE_TYPES else "ground → aircraft"
        assert direction == expected, name
    assert seen == {int(t) for t in messages.MsgType}


def test_legacy_field_tables_match_the_codec() -> None:
    section = _section(_doc("legacy-protocol.md"), "## Message types")
    seen: set[int] = set()
    for title, body in _subsections(section, 3):
        m = re.fullmatch(r"0x([0-9A-F]{2}) (\w+) \((\d+) bytes\)", title)
        if m is None:
            continue
        code = int(m.group(1), 16)
        seen.add(code)
        assert codec.layout_of(code) == (m.group(2), int(m.group(3))), title
        expected: list[tuple[int, str, str | None]] = []  # offset, field, type (None: reserved)
        offset = codec.HEADER_SIZE
        reserved_sizes: list[int] = []
        for name, wire in codec.wire_fields(codec.payload_class(code)):
            wtype = _wire_type(wire)
            expected.append((offset, name, wtype))
            offset += _type_size(wtype)
            if wire.pad_after:
                expected.append((offset, "reserved", None))
                reserved_sizes.append(wire.pad_after)
                offset += wire.pad_after
        assert offset == int(m.group(3)), title
        got: list[tuple[int, str, str | None]] = []
        got_reserved: list[int] = []
        for offset_cell, type_cell, field_cell, _meaning in _table(body, "offset"):
            if field_cell == "reserved":
                got.append((int(offset_cell), "reserved", None))
                got_reserved.append(_type_size(type_cell))
            else:
                got.append((int(offset_cell), _ticked(field_cell), type_cell))
        assert got == expected, title
        assert got_reserved == reserved_sizes, title
    assert seen == {int(t) for t in messages.MsgType}


def test_legacy_header_table_reads_every_vector() -> None:
    rows = _table(_section(_doc("legacy-protocol.md"), "## Header (16 bytes, every datagram)"),
                  "offset")
    assert sum(int(r[1]) for r in rows) == codec.HEADER_SIZE
    for vec in _vectors():
        data = bytes.fromhex(vec["hex"])
        decoded = codec.decode(data)
        assert isinstance(decoded, codec.Decoded), decoded
        position = 0
        for offset_cell, size_cell, type_cell, field_cell, _meaning in rows:
            assert int(offset_cell) == position and _type_size(type_cell) == int(size_cell)
            value = struct.unpack_from("<" + _HEADER_CODES[type_cell], data, position)[0]
            assert value == getattr(decoded.header, _ticked(field_cell)), (vec["name"], field_cell)
            position += int(size_cell)


def test_legacy_worked_examples_decode_as_shown() -> None:
    section = _section(_doc("legacy-protocol.md"), "## Worked examples")
    by_hex = {v["hex"]: v for v in _vectors()}
    examples = [(t, b) for t, b in _subsections(section, 3) if t.startswith("Example: ")]
    assert len(examples) >= 2
    for title, body in examples:
        blocks = [lines for info, lines in _code_blocks(body) if info == ""]
        assert len(blocks) == 1, title
        data = bytes.fromhex(" ".join(blocks[0]))
        vec = by_hex.get(data.hex())
        assert vec is not None, f"{title}: the hex is not a datagram of legacy-udp.json"
        decoded = codec.decode(data)
        assert isinstance(decoded, codec.Decoded), decoded
        assert title == f"Example: {vec['name']}" == f"Example: {decoded.name}"
        covered = 0
        for offset_cell, bytes_cell, field_cell, value_cell in _table(body, "offset"):
            offset = int(offset_cell)
            raw = _hex(bytes_cell)
            assert offset == covered, f"{title}: gap before offset {offset}"
            covered = offset + len(raw)
            assert data[offset:covered] == raw, f"{title}: bytes at offset {offset}"
            if field_cell == "reserved":
                assert raw == bytes(len(raw)) and _number(value_cell) == 0
                continue
            name = _ticked(field_cell)
            source: Any = decoded.header if offset < codec.HEADER_SIZE else decoded.payload
            actual = getattr(source, name)
            shown = _number(value_cell)
            if isinstance(actual, float):
                assert actual in (shown, _f32(shown)), f"{title}: {name} = {actual}"
            else:
                assert actual == shown, f"{title}: {name} = {actual}"
        assert covered == len(data) == vec["size"], title


def test_legacy_ack_results_and_ports_match_the_codec() -> None:
    text = _doc("legacy-protocol.md")
    rows = _table(_section(text, "## Commands and acknowledgements"), "result")
    assert {int(r[0]): _ticked(r[1]) for r in rows} == {int(r): r.name for r in messages.AckResult}
    transport = _table(_section(text, "## Transport"), "datagrams")
    ports = {row[0].split()[0]: re.findall(r"\*\*(\d+)\*\*", row[3]) for row in transport}
    assert ports["messages"] == [str(messages.DEFAULT_MONITOR_PORT)]
    assert ports["commands"] == [str(messages.DEFAULT_COMMAND_PORT)]


# -- both pages -------------------------------------------------------------------------------

# Built from pieces so that this file does not itself name the paths it looks for.
_MACHINE_PATH = re.compile(
    r"(?<![\w.~$}-])/(?:" + "|".join(["wo" + "rk", "home", "root", "tmp", "mnt"]) + r")\b"
    r"|\.\./" + "shared" + r"|(?<![\w-])" + "shared" + r"/"
)


@pytest.mark.parametrize("name", ["logs.md", "legacy-protocol.md"])
def test_pages_name_no_path_outside_the_repository(name: str) -> None:
    text = _doc(name)
    found = [line for line in text.splitlines() if _MACHINE_PATH.search(line)]
    assert not found, f"docs/{name} names paths users do not have: {found}"
    for path in re.findall(r"`(tests/data/vectors/[^`]+)`", text):
        assert (REPO / path).is_file(), f"docs/{name} cites missing {path}"
