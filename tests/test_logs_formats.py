"""Format strings: the contract's conversion table, errors, and C-exact rendering.

The reference for rendering is the C library's own snprintf (through ctypes), not a reading of
the standard; Python's ``%`` is checked where it agrees.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math
import struct
from typing import Literal

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from companion.logs.formats import MAX_WIDTH, FormatError, parse_format

_LIBC_NAME = ctypes.util.find_library("c")
LIBC = ctypes.CDLL(_LIBC_NAME) if _LIBC_NAME else None
needs_libc = pytest.mark.skipif(LIBC is None, reason="no C library to compare with")

# (conversion as written, numpy dtype) for every row of the contract's table.
TABLE = [
    ("%c", "i1"), ("%hhd", "i1"), ("%hhi", "i1"),
    ("%hhu", "u1"), ("%hhx", "u1"), ("%hhX", "u1"), ("%hho", "u1"),
    ("%hd", "i2"), ("%hi", "i2"),
    ("%hu", "u2"), ("%hx", "u2"), ("%hX", "u2"), ("%ho", "u2"),
    ("%d", "i4"), ("%i", "i4"), ("%ld", "i4"), ("%li", "i4"),
    ("%u", "u4"), ("%x", "u4"), ("%X", "u4"), ("%o", "u4"), ("%lu", "u4"), ("%lx", "u4"), ("%lX", "u4"),
    ("%lld", "i8"), ("%lli", "i8"),
    ("%llu", "u8"), ("%llx", "u8"), ("%llX", "u8"),
    ("%f", "f4"), ("%e", "f4"), ("%g", "f4"), ("%E", "f4"), ("%G", "f4"),
    ("%lf", "f8"), ("%le", "f8"), ("%lg", "f8"),
]  # fmt: skip


def c_printf(fmt: str, spec_values: list[tuple[str, int | float]]) -> bytes:
    """What the C library prints for `fmt` with values passed as C would pass them."""
    assert LIBC is not None
    args: list[object] = []
    for conv, value in spec_values:
        if conv in "feEgGF":
            args.append(ctypes.c_double(float(value)))
        elif conv.startswith("ll"):
            args.append(ctypes.c_ulonglong(int(value) & (2**64 - 1)))
        elif conv.startswith("l"):
            args.append(ctypes.c_long(int(value)))
        else:
            args.append(ctypes.c_int(int(value)))
    size = 16384
    buf = ctypes.create_string_buffer(size)
    n = LIBC.snprintf(buf, size, fmt.encode("latin-1"), *args)
    assert 0 <= n < size
    return buf.raw[:n]


def _kind(conv_length: str, conv: str) -> str:
    if conv in "feEgGF":
        return conv
    return conv_length + conv


@pytest.mark.parametrize(("conv", "dtype"), TABLE)
def test_every_conversion_of_the_table_has_its_field_type(conv: str, dtype: str) -> None:
    spec = parse_format(f"x={conv};")
    assert spec.n_fields == 1
    assert spec.conversions[0].dtype == np.dtype("<" + dtype)
    assert spec.size == np.dtype(dtype).itemsize
    assert spec.literals == ("x=", ";")


def test_layout_is_packed_little_endian_in_order() -> None:
    spec = parse_format("%hhu,%d,%lf,%hd")
    assert spec.struct_format == "<Bidh"
    assert spec.size == 1 + 4 + 8 + 2
    dt = spec.dtype(["a", "b", "c", "d"])
    assert dt.itemsize == 15 and dt.fields is not None
    assert [dt.fields[n][1] for n in "abcd"] == [0, 1, 5, 13]


def test_percent_percent_is_a_literal() -> None:
    spec = parse_format("100%% of %d%%")
    assert spec.n_fields == 1
    assert spec.render([7]) == "100% of 7%"


@pytest.mark.parametrize(
    "bad",
    [
        "%s",
        "%p",
        "%n",
        "%*d",
        "%1$d",
        "abc%",
        "%Lf",
        "%hf",
        "%lc",
        "%q",
        "%5%",
        "%zd",
        f"%{MAX_WIDTH + 1}d",
        "a\x00b",
    ],
)
def test_unsupported_conversions_raise_format_error_with_position(bad: str) -> None:
    with pytest.raises(FormatError) as err:
        parse_format(bad)
    assert repr(bad)[1:-1][:3] in str(err.value) or "NUL" in str(err.value)
    assert "character" in str(err.value)


def test_byte_array_formats() -> None:
    assert parse_format("%hhu").byte_array_ok
    assert parse_format("%c").byte_array_ok
    assert parse_format("v=%02hhX").byte_array_ok
    assert not parse_format("%hu").byte_array_ok
    assert not parse_format("%hhu,%hhu").byte_array_ok


# Known differences between C and Python's `%`, rendered as C does.
@pytest.mark.parametrize(
    ("fmt", "value", "expected"),
    [
        ("%#x", 0, "0"),
        ("%#o", 0, "0"),
        ("%#o", 8, "010"),
        ("%.0d", 0, ""),
        ("%05.3d", 5, "  005"),
        ("%+u", 5, "5"),
        ("% x", 5, "5"),
        ("%#08.3x", 5, "   0x005"),
        ("%#X", 255, "0XFF"),
        ("%08f", math.inf, "     inf"),
        ("%08f", -math.nan, "    -nan"),
        ("%+f", math.nan, "+nan"),
        ("%E", math.inf, "INF"),
        ("%-6e", -math.inf, "-inf  "),
        ("%5c", 65, "    A"),
        ("%-3c", -1, "\xff  "),
        ("%+.3d", 7, "+007"),
    ],
)
def test_c_semantics_where_python_differs(fmt: str, value: float, expected: str) -> None:
    spec = parse_format(fmt)
    assert spec.render([value]) == expected
    col = np.array([value], dtype=spec.conversions[0].dtype)
    template, lists = spec.batch([col])
    assert template % tuple(x[0] for x in lists) == expected


# -- property: the renderer equals the C library -----------------------------------------------

_FLAGS = st.lists(st.sampled_from("-+ #0"), max_size=4).map("".join)
_NUM = st.one_of(st.none(), st.integers(0, 25))


@st.composite
def conversions(draw: st.DrawFn) -> str:
    conv, _ = draw(st.sampled_from(TABLE))
    flags = draw(_FLAGS)
    width = draw(_NUM)
    prec = draw(st.one_of(st.none(), st.just(""), st.integers(0, 20)))
    body = conv[1:]
    return (
        "%"
        + flags
        + ("" if width is None else str(width))
        + ("" if prec is None else "." + str(prec))
        + body
    )


_LITERAL = st.text(
    alphabet=st.characters(min_codepoint=32, max_codepoint=126, exclude_characters="%"), max_size=4
)


@st.composite
def formats(draw: st.DrawFn) -> str:
    parts = [draw(_LITERAL)]
    for _ in range(draw(st.integers(1, 5))):
        parts.append(draw(conversions()))
        parts.append(draw(st.one_of(_LITERAL, st.just(","), st.just("%%"))))
    return "".join(parts)


def value_for(dtype: np.dtype) -> st.SearchStrategy[int | float]:
    if dtype.kind == "f":
        width: Literal[32, 64] = 32 if dtype.itemsize == 4 else 64
        return st.floats(width=width, allow_nan=True, allow_infinity=True)
    info = np.iinfo(dtype)
    return st.integers(int(info.min), int(info.max))


@needs_libc
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_rendering_equals_the_c_library(data: st.DataObject) -> None:
    fmt = data.draw(formats())
    spec = parse_format(fmt)
    values = [data.draw(value_for(c.dtype)) for c in spec.conversions]
    # Values as stored in the file (float32 fields rounded to float32).
    stored = list(struct.unpack(spec.struct_format, struct.pack(spec.struct_format, *values)))
    expected = c_printf(
        fmt, [(_kind(c.length, c.conv), v) for c, v in zip(spec.conversions, stored, strict=True)]
    )
    assert spec.render(stored).encode("latin-1") == expected
    cols = [np.array([v], dtype=c.dtype) for c, v in zip(spec.conversions, stored, strict=True)]
    template, lists = spec.batch(cols)
    assert (template % tuple(x[0] for x in lists)).encode("latin-1") == expected


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_rendering_agrees_with_python_percent_where_python_is_exact(data: st.DataObject) -> None:
    fmt = data.draw(formats())
    spec = parse_format(fmt)
    for conv in spec.conversions:
        py = conv.python_spec
        if py is None or conv.conv == "c":
            continue
        value = data.draw(value_for(conv.dtype))
        if conv.is_float:
            value = float(np.array(value, dtype=conv.dtype))
            if not math.isfinite(value):
                continue
        # Python's % ignores length modifiers and has no %u/%i: the spec is the C one minus those.
        assert conv.render(value) == py % value
