"""Flight logs: the binary record format of the thesis (Appendix B), its writer, reader and tools.

The format, byte by byte, and the tools are documented in docs/logs.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from companion.core.lazy import lazy_exports

if TYPE_CHECKING:
    from companion.logs.convert import convert_file
    from companion.logs.formats import FormatError, FormatSpec, parse_format
    from companion.logs.producers import RawLog, ThreadLog
    from companion.logs.reader import read_log, read_log_bytes
    from companion.logs.streams import Damage, LogFile, LogFormatError, Marker, Stream
    from companion.logs.writer import LogService, write_run_json

_EXPORTS = {
    "convert_file": "companion.logs.convert",
    "FormatError": "companion.logs.formats",
    "FormatSpec": "companion.logs.formats",
    "parse_format": "companion.logs.formats",
    "Damage": "companion.logs.streams",
    "LogFile": "companion.logs.streams",
    "LogFormatError": "companion.logs.streams",
    "Marker": "companion.logs.streams",
    "Stream": "companion.logs.streams",
    "read_log": "companion.logs.reader",
    "read_log_bytes": "companion.logs.reader",
    "LogService": "companion.logs.writer",
    "RawLog": "companion.logs.producers",
    "ThreadLog": "companion.logs.producers",
    "write_run_json": "companion.logs.writer",
}

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

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
