"""Declaring how a record dataclass is logged, on its own fields.

A field made with `logged("%.3f")` carries its printf-style log format (and optionally another
column name and a scale, for a unit change such as seconds to milliseconds) in its metadata, so
the record's definition, its log format and the values of a log call come from one description
(`companion.logs.layout.RecordLayout` reads it). Fields without it are not logged.
"""

from __future__ import annotations

import dataclasses
from typing import Any

__all__ = ["LOG_KEY", "LogColumn", "logged"]

LOG_KEY = "companion.log"


@dataclasses.dataclass(frozen=True)
class LogColumn:
    fmt: str
    """printf-style conversion of the log's Format Definition (``%.3f``, ``%hhu``...)."""
    column: str = ""
    """Column name in the log; empty: the field's name."""
    scale: float = 1.0
    """Multiplier applied before logging (1e3 logs a value in seconds as milliseconds)."""


def logged(fmt: str, *, column: str = "", scale: float = 1.0, default: Any = None) -> Any:
    """A dataclass field with a default that is logged with `fmt` (see the module docstring)."""
    return dataclasses.field(default=default,
                             metadata={LOG_KEY: LogColumn(fmt, column, scale)})
