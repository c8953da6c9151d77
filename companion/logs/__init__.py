"""Flight logs: the binary record format of the thesis (Appendix B), its writer, reader and tools.

The format, byte by byte, and the tools are documented in docs/logs.md.
"""

from __future__ import annotations

from companion.logs.convert import convert_file
from companion.logs.formats import FormatError, FormatSpec, parse_format
from companion.logs.reader import (
    Damage,
    LogFile,
    LogFormatError,
    Marker,
    Stream,
    read_log,
    read_log_bytes,
)
from companion.logs.writer import LogService, RawLog, ThreadLog, write_run_json

__all__ = [
    "Damage",
    "FormatError",
    "FormatSpec",
    "LogFile",
    "LogFormatError",
    "LogService",
    "Marker",
    "RawLog",
    "Stream",
    "ThreadLog",
    "convert_file",
    "parse_format",
    "read_log",
    "read_log_bytes",
    "write_run_json",
]
