"""A log format read from a record dataclass whose fields say how they are logged.

`RecordLayout.of(GpsFix)` gives the Format Definition (printf format and column names) and
`values(fix)` gives the arguments of the matching `ThreadLog.log` call, from the fields made with
`companion.core.logged.logged`. A missing value is logged as NaN in a float column and 0 in an
integer one, because the binary format has no null.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import cache
from typing import Any

from companion.core.logged import LOG_KEY, LogColumn

__all__ = ["RecordLayout"]

_INT_CONVERSIONS = frozenset("diuxXc")


@dataclass(frozen=True)
class _Column:
    attr: str
    name: str
    fmt: str
    scale: float
    integer: bool


@dataclass(frozen=True)
class RecordLayout:
    columns: tuple[_Column, ...]

    @staticmethod
    @cache
    def of(record_type: type) -> RecordLayout:
        if not dataclasses.is_dataclass(record_type):
            raise TypeError(f"{record_type.__name__} is not a dataclass")
        cols = []
        for f in dataclasses.fields(record_type):
            spec = f.metadata.get(LOG_KEY)
            if isinstance(spec, LogColumn):
                cols.append(_Column(f.name, spec.column or f.name, spec.fmt, spec.scale,
                                    spec.fmt[-1] in _INT_CONVERSIONS))
        if not cols:
            raise TypeError(f"{record_type.__name__} declares no logged field")
        return RecordLayout(tuple(cols))

    @property
    def fmt(self) -> str:
        return ",".join(c.fmt for c in self.columns)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.columns]

    def values(self, record: Any) -> tuple[Any, ...]:
        out: list[Any] = []
        for c in self.columns:
            v = getattr(record, c.attr)
            if c.integer:
                out.append(0 if v is None else int(v))
            elif v is None:
                out.append(math.nan)
            else:
                out.append(float(v) * c.scale if c.scale != 1.0 else float(v))
        return tuple(out)
