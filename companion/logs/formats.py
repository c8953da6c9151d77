"""printf-like format strings of the flight log: parsing, field layout and C-exact rendering.

A format string both describes the binary layout of a record (its conversions, in order, are the
packed little-endian fields, sized as on the ILP32 target of the original system) and says how a
record is rendered as text. The renderer must print exactly what C's printf would, because the
text logs of the original tools are the reference. Python's ``%`` operator agrees with C for most
conversions, so it does the bulk of the work; the cases where the two differ (``#`` with ``x`` and
``o``, integer precision, ``+``/space with unsigned conversions, inf/nan) are rendered here.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

__all__ = [
    "MAX_WIDTH",
    "Conversion",
    "FormatError",
    "FormatSpec",
    "parse_format",
]

#: Largest width or precision accepted: bounds the text a single field can produce.
MAX_WIDTH = 4096

# (length modifier, conversion) -> (struct code, numpy dtype). The table of the contract, plus
# the obvious siblings it does not list (%lo, %llo, %F, %lE, %lG, %lF), which C accepts too.
_FIELD_TYPES: dict[tuple[str, str], tuple[str, str]] = {}


def _register(lengths: str, convs: str, code: str, dtype: str) -> None:
    for length in lengths.split(","):
        for conv in convs:
            _FIELD_TYPES[(length, conv)] = (code, dtype)


_register("", "c", "b", "<i1")
_register("hh", "di", "b", "<i1")
_register("hh", "uxXo", "B", "<u1")
_register("h", "di", "h", "<i2")
_register("h", "uxXo", "H", "<u2")
_register(",l", "di", "i", "<i4")
_register(",l", "uxXo", "I", "<u4")
_register("ll", "di", "q", "<i8")
_register("ll", "uxXo", "Q", "<u8")
_register("", "feEgGF", "f", "<f4")
_register("l", "feEgGF", "d", "<f8")

_SIGNED = frozenset("dic")
_FLOAT = frozenset("feEgGF")

_SPEC_RE = re.compile(
    r"%(?P<flags>[-+ #0]*)(?P<width>[0-9]+)?(?:\.(?P<prec>[0-9]*))?(?P<length>hh|h|ll|l)?"
    r"(?P<conv>[diouxXcfFeEgG%])"
)


class FormatError(ValueError):
    """A format string that the log format cannot describe; says what and at which character."""


@dataclass(frozen=True)
class Conversion:
    """One ``%`` conversion of a format string and the binary field it stands for."""

    spec: str  # the conversion as written, e.g. "%8.3f"
    flags: str
    width: int | None
    precision: int | None
    length: str
    conv: str
    struct_code: str
    dtype: np.dtype[Any]
    position: int  # character offset of the '%' in the format string

    @property
    def is_float(self) -> bool:
        return self.conv in _FLOAT

    @property
    def python_spec(self) -> str | None:
        """The Python ``%`` spec that prints what C prints for every finite value, or None.

        None means no Python spec agrees for all values, and `render` must be used.
        """
        return _python_spec(self)

    def render(self, value: int | float) -> str:
        """The text C's printf produces for this conversion and `value` (the field's value)."""
        if self.conv in _FLOAT:
            fvalue = float(value)
            if not math.isfinite(fvalue):
                return _render_nonfinite(self, fvalue)
            return (_python_spec(self) or "") % fvalue
        if self.conv == "c":
            return _pad(self, chr(int(value) & 0xFF), zero_ok=False)
        return _render_int(self, int(value))


def _python_spec(c: Conversion) -> str | None:
    flags = c.flags
    if c.conv in _FLOAT:
        conv = c.conv
    elif c.conv == "c":
        flags = "-" if "-" in flags else ""
        conv = "c"
        return "%" + flags + ("" if c.width is None else str(c.width)) + conv
    else:
        if "#" in flags or c.precision is not None:
            return None
        if c.conv not in _SIGNED:
            flags = flags.replace("+", "").replace(" ", "")
        conv = {"i": "d", "u": "d"}.get(c.conv, c.conv)
    width = "" if c.width is None else str(c.width)
    prec = "" if c.precision is None else "." + str(c.precision)
    return "%" + flags + width + prec + conv


def _pad(c: Conversion, body: str, *, zero_ok: bool, sign_len: int = 0) -> str:
    width = c.width or 0
    if len(body) >= width:
        return body
    if "-" in c.flags:
        return body.ljust(width)
    if zero_ok and "0" in c.flags:
        return body[:sign_len] + body[sign_len:].rjust(width - sign_len, "0")
    return body.rjust(width)


def _render_int(c: Conversion, value: int) -> str:
    negative = value < 0
    magnitude = -value if negative else value
    if c.conv in "xX":
        digits = format(magnitude, c.conv)
    elif c.conv == "o":
        digits = format(magnitude, "o")
    else:
        digits = str(magnitude)
    if c.precision is not None:
        digits = "" if (c.precision == 0 and magnitude == 0) else digits.zfill(c.precision)
    prefix = ""
    if "#" in c.flags:
        if c.conv == "o" and not digits.startswith("0"):
            digits = "0" + digits
        elif c.conv in "xX" and magnitude != 0:
            prefix = "0" + c.conv
    sign = ""
    if c.conv in _SIGNED:
        if negative:
            sign = "-"
        elif "+" in c.flags:
            sign = "+"
        elif " " in c.flags:
            sign = " "
    head = sign + prefix
    return _pad(c, head + digits, zero_ok=c.precision is None, sign_len=len(head))


def _render_nonfinite(c: Conversion, value: float) -> str:
    word = "nan" if math.isnan(value) else "inf"
    if c.conv.isupper():
        word = word.upper()
    if math.copysign(1.0, value) < 0:
        sign = "-"
    elif "+" in c.flags:
        sign = "+"
    elif " " in c.flags:
        sign = " "
    else:
        sign = ""
    # glibc pads inf/nan with spaces even with the '0' flag.
    return _pad(c, sign + word, zero_ok=False)


@dataclass(frozen=True)
class FormatSpec:
    """A parsed format string: literal pieces around its conversions, and the record layout."""

    text: str
    conversions: tuple[Conversion, ...]
    literals: tuple[str, ...]  # len(conversions) + 1 pieces of literal text (with %% resolved)
    struct_format: str  # struct module format of the data, little-endian, no padding
    size: int  # bytes of data a Data Block of this format carries

    @property
    def n_fields(self) -> int:
        return len(self.conversions)

    @property
    def byte_array_ok(self) -> bool:
        """Whether Byte Array records may use this format: one conversion of one byte."""
        return len(self.conversions) == 1 and self.conversions[0].dtype.itemsize == 1

    @property
    def field_dtypes(self) -> list[np.dtype[Any]]:
        return [c.dtype for c in self.conversions]

    def dtype(self, names: Sequence[str] | None = None) -> np.dtype[Any]:
        """Packed structured dtype of the data (no time), with `names` or f0, f1, ..."""
        if names is None:
            names = [f"f{i}" for i in range(self.n_fields)]
        if len(names) != self.n_fields:
            raise ValueError(f"{len(names)} names for {self.n_fields} fields of {self.text!r}")
        return np.dtype([(n, c.dtype) for n, c in zip(names, self.conversions, strict=True)])

    def render(self, values: Sequence[int | float]) -> str:
        """The whole format applied to one record's field values, exactly as C's printf."""
        if len(values) != len(self.conversions):
            raise ValueError(
                f"format {self.text!r} has {len(self.conversions)} fields, got {len(values)}"
            )
        parts = [self.literals[0]]
        for conv, value, lit in zip(self.conversions, values, self.literals[1:], strict=True):
            parts.append(conv.render(value))
            parts.append(lit)
        return "".join(parts)

    def batch(self, columns: Sequence[np.ndarray]) -> tuple[str, list[list[Any]]]:
        """A Python ``%`` template and per-field Python lists that render a batch of records.

        Each column goes through Python's ``%`` when that is exact for every value in it;
        otherwise it is rendered here into strings and the template takes it with ``%s``.
        ``template % row`` for each row of ``zip(*lists)`` then equals C's printf output.
        """
        pieces = [_escape(self.literals[0])]
        lists: list[list[Any]] = []
        for conv, col, lit in zip(self.conversions, columns, self.literals[1:], strict=True):
            spec = _python_spec(conv)
            if conv.conv == "c" and spec is not None:
                lists.append(np.asarray(col).astype(np.uint8).tolist())
            elif spec is not None and (not conv.is_float or bool(np.isfinite(col).all())):
                lists.append(np.asarray(col).tolist())
            else:
                lists.append([conv.render(v) for v in np.asarray(col).tolist()])
                spec = "%s"
            pieces.append(spec)
            pieces.append(_escape(lit))
        return "".join(pieces), lists


def _escape(literal: str) -> str:
    return literal.replace("%", "%%")


@lru_cache(maxsize=1024)
def parse_format(text: str) -> FormatSpec:
    """Parse a format string of the log contract.

    Raises FormatError naming the character position of anything the contract does not
    describe (``%s``, ``*`` widths, positional arguments, a lone ``%`` at the end...).
    """
    if "\x00" in text:
        raise FormatError(
            f"format string {text!r} contains a NUL at character {text.index(chr(0))}"
        )
    conversions: list[Conversion] = []
    literals: list[str] = []
    current: list[str] = []
    pos = 0
    while True:
        nxt = text.find("%", pos)
        if nxt < 0:
            current.append(text[pos:])
            break
        current.append(text[pos:nxt])
        m = _SPEC_RE.match(text, nxt)
        if m is None:
            bad = text[nxt : nxt + 6]
            raise FormatError(
                f"format string {text!r}: unsupported conversion {bad!r} at character {nxt}"
            )
        if m.group("conv") == "%":
            if m.group(0) != "%%":
                raise FormatError(
                    f"format string {text!r}: {m.group(0)!r} at character {nxt} (use '%%')"
                )
            current.append("%")
            pos = m.end()
            continue
        conv = m.group("conv")
        length = m.group("length") or ""
        types = _FIELD_TYPES.get((length, conv))
        if types is None:
            raise FormatError(
                f"format string {text!r}: conversion {m.group(0)!r} at character {nxt} "
                f"has no field type in the log contract"
            )
        width = int(m.group("width")) if m.group("width") is not None else None
        prec_text = m.group("prec")
        precision = None if prec_text is None else int(prec_text or "0")
        for what, number in (("width", width), ("precision", precision)):
            if number is not None and number > MAX_WIDTH:
                raise FormatError(
                    f"format string {text!r}: {what} {number} at character {nxt} "
                    f"exceeds {MAX_WIDTH}"
                )
        literals.append("".join(current))
        current = []
        conversions.append(
            Conversion(
                spec=m.group(0),
                flags=m.group("flags"),
                width=width,
                precision=precision,
                length=length,
                conv=conv,
                struct_code=types[0],
                dtype=np.dtype(types[1]),
                position=nxt,
            )
        )
        pos = m.end()
    literals.append("".join(current))
    struct_format = "<" + "".join(c.struct_code for c in conversions)
    size = sum(c.dtype.itemsize for c in conversions)
    return FormatSpec(
        text=text,
        conversions=tuple(conversions),
        literals=tuple(literals),
        struct_format=struct_format,
        size=size,
    )
