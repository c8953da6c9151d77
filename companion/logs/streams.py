"""What a read of a binary flight log gives: `LogFile`, its `Stream`s, `Marker`s and `Damage`,
or `LogFormatError`; and how a stream's columns are named (`column_names`).

These are what callers of `companion.logs.reader.read_log` (the converter, the dataset loader,
the reports, the live view) hold and pass around; they are separate from the reader so that
code which only handles a log already read does not depend on how it was parsed, and so that
the text-mode writer names its CSV columns with the same rule as the reader.

Layout (see docs/logs.md):

* A Data Block format gives a structured array with ``time_s`` (float64 seconds) followed by one
  typed field per conversion, named from the Format Comment (else ``c1, c2, ...``).
* A Byte Array format gives a "long" structured array, one row per element: ``time_s``,
  ``record`` (the record's number in its stream), ``element`` (position in the record) and the
  value (named from a one-name comment, else ``value``). `Stream.arrays()` gives one 1-D array
  per record instead.
* Redefining an index: records are grouped into *streams* by (index, record kind, format string,
  column names); a redefinition that changes any of these starts a new stream, an identical one
  continues the old stream. `LogFile.data(index)` concatenates the streams of an index when they
  share one layout and otherwise refuses and points at `LogFile.streams_of(index)`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from companion.logs.formats import FormatSpec
from companion.logs.records import NS_PER_S

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["Damage", "LogFile", "LogFormatError", "Marker", "Stream", "column_names"]


class LogFormatError(ValueError):
    """A damaged or malformed log; carries the file name, the byte offset and the kind.

    kind is one of: unknown_type, past_eof, undefined_index, length_mismatch, bad_definition.
    """

    def __init__(self, path: str, offset: int, message: str, kind: str) -> None:
        self.path = path
        self.offset = offset
        self.reason = message
        self.kind = kind
        super().__init__(f"{path}: byte offset {offset}: {message}")


@dataclass(frozen=True)
class Marker:
    """A Begin Data or End Data record."""

    kind: str  # "begin" or "end"
    time_ns: int
    offset: int

    @property
    def time_s(self) -> float:
        return self.time_ns / NS_PER_S


@dataclass(frozen=True)
class Damage:
    """A corrupt region skipped by a salvaging read."""

    offset: int
    kind: str
    message: str
    skipped_bytes: int


@dataclass
class Stream:
    """The records of one format index under one definition (see the module docstring).

    A Byte Array stream keeps its elements as one flat array (`values`, record after record,
    with `lengths`); its long table `data` (one 15-byte row per element) is built on first use.
    """

    index: int
    kind: str  # "block" (Data Block) or "array" (Byte Array)
    spec: FormatSpec
    columns: tuple[str, ...]
    number: int  # 1 for the first stream of its index, 2 for the next...
    definition_offset: int
    time_ns: np.ndarray  # int64 per record, exact
    offsets: np.ndarray  # int64 byte offset of each record
    lengths: np.ndarray | None = None  # elements per record (arrays only)
    values: np.ndarray | None = None  # arrays: every element, in file order
    time_s: np.ndarray | None = None  # arrays: float64 seconds per record
    _data: np.ndarray | None = field(default=None, repr=False)

    @property
    def data(self) -> np.ndarray:
        """The structured array: one row per record (blocks) or per element (arrays)."""
        if self._data is None:
            self._data = self._long_table()
        return self._data

    def _long_table(self) -> np.ndarray:
        assert self.values is not None and self.lengths is not None and self.time_s is not None
        lens = self.lengths.astype(np.int64)
        total = int(self.values.size)
        out = np.empty(
            total,
            dtype=np.dtype(
                [
                    ("time_s", "<f8"),
                    ("record", "<u4"),
                    ("element", "<u2"),
                    (self.columns[0], self.values.dtype),
                ]
            ),
        )
        before = np.cumsum(lens) - lens
        out[self.columns[0]] = self.values
        out["time_s"] = np.repeat(self.time_s, lens)
        out["record"] = np.repeat(np.arange(self.offsets.size), lens)
        out["element"] = np.arange(total) - np.repeat(before, lens)
        return out

    def head(self, k: int) -> Stream:
        """The stream of its first `k` records."""
        if self.kind != "array":
            return replace(self, time_ns=self.time_ns[:k], offsets=self.offsets[:k],
                           _data=self.data[:k])
        assert self.lengths is not None and self.values is not None and self.time_s is not None
        n_values = int(self.lengths[:k].sum())
        return replace(
            self, time_ns=self.time_ns[:k], offsets=self.offsets[:k], lengths=self.lengths[:k],
            values=self.values[:n_values], time_s=self.time_s[:k],
            _data=None if self._data is None else self._data[:n_values],
        )

    @property
    def format(self) -> str:
        return self.spec.text

    @property
    def n_records(self) -> int:
        return int(self.offsets.size)

    @property
    def value_field(self) -> str:
        """For arrays, the name of the element field of `data`."""
        return self.columns[0]

    def arrays(self) -> list[np.ndarray]:
        """One 1-D array of elements per record (arrays only)."""
        if self.kind != "array" or self.lengths is None or self.values is None:
            raise ValueError(f"format index {self.index} holds Data Blocks, not Byte Arrays")
        return np.split(self.values, np.cumsum(self.lengths)[:-1]) if self.lengths.size else []

    def to_pandas(self) -> pd.DataFrame:
        import pandas as pd

        return pd.DataFrame({name: self.data[name] for name in self.data.dtype.names or ()})


@dataclass
class LogFile:
    """Everything read from one binary log."""

    path: str
    size_bytes: int
    streams: list[Stream]
    markers: list[Marker]
    damage: list[Damage]
    truncated_bytes: int
    record_count: int
    warnings: list[str] = field(default_factory=list)

    @property
    def indexes(self) -> list[int]:
        return sorted({s.index for s in self.streams})

    @property
    def closed_cleanly(self) -> bool:
        """True when the last marker is an End Data and no record was cut short."""
        return bool(self.markers) and self.markers[-1].kind == "end" and not self.truncated_bytes

    @property
    def skipped_bytes(self) -> int:
        return sum(d.skipped_bytes for d in self.damage)

    @property
    def skipped_records(self) -> int:
        """Corrupt records skipped by salvage (one per damaged region)."""
        return len(self.damage)

    def streams_of(self, index: int) -> list[Stream]:
        found = [s for s in self.streams if s.index == index]
        if not found:
            raise KeyError(f"{self.path}: no format index {index} (have {self.indexes})")
        return found

    def begin_end_pairs(self) -> list[tuple[Marker | None, Marker | None]]:
        """Begin/End markers paired in file order; a missing half is None."""
        pairs: list[tuple[Marker | None, Marker | None]] = []
        pending: Marker | None = None
        for m in self.markers:
            if m.kind == "begin":
                if pending is not None:
                    pairs.append((pending, None))
                pending = m
            else:
                pairs.append((pending, m))
                pending = None
        if pending is not None:
            pairs.append((pending, None))
        return pairs

    def data(self, index: int) -> np.ndarray:
        """The structured array of a format index (all its streams, when they share a layout)."""
        streams = self.streams_of(index)
        if len(streams) == 1:
            return streams[0].data
        first = streams[0]
        for s in streams[1:]:
            if s.data.dtype != first.data.dtype or s.kind != first.kind:
                raise ValueError(
                    f"{self.path}: format index {index} changes layout at byte offset "
                    f"{s.definition_offset} ({first.format!r} -> {s.format!r}); "
                    f"use streams_of({index}) or to_pandas({index})"
                )
        if first.kind == "array":
            raise ValueError(
                f"{self.path}: format index {index} has {len(streams)} array streams; "
                f"use streams_of({index})"
            )
        offsets = np.concatenate([s.offsets for s in streams])
        order = np.argsort(offsets, kind="stable")
        return np.concatenate([s.data for s in streams])[order]

    __getitem__ = data

    def time_ns(self, index: int) -> np.ndarray:
        """Exact record times (int64 ns) of a format index, in file order."""
        streams = self.streams_of(index)
        offsets = np.concatenate([s.offsets for s in streams])
        times = np.concatenate([s.time_ns for s in streams])
        return times[np.argsort(offsets, kind="stable")]

    def to_pandas(self, index: int) -> pd.DataFrame:
        """A DataFrame of a format index; streams with other columns are aligned (NaN-filled)."""
        import pandas as pd

        streams = self.streams_of(index)
        frames = [s.to_pandas() for s in streams]
        if len(frames) == 1:
            return frames[0]
        keys = np.concatenate(
            [s.offsets if s.lengths is None else np.repeat(s.offsets, s.lengths) for s in streams]
        )
        frame = pd.concat(frames, ignore_index=True)
        return frame.iloc[np.argsort(keys, kind="stable")].reset_index(drop=True)



def _clean_names(names: list[str], count: int) -> tuple[str, ...]:
    out: list[str] = []
    seen = {"time_s"}
    for k in range(count):
        name = names[k].strip() if k < len(names) else ""
        if not name:
            name = f"c{k + 1}"
        base, n = name, 2
        while name in seen:
            name = f"{base}_{n}"
            n += 1
        seen.add(name)
        out.append(name)
    return tuple(out)


def column_names(comment: Sequence[str] | None, spec: FormatSpec, kind: str) -> tuple[str, ...]:
    """Field names of a stream from its Format Comment (shared with the text-mode writer).

    Data Blocks: the comment's names when there is one per field (blank ones become ``c<k>``,
    repeats and ``time_s`` get a ``_2`` suffix), else ``c1, c2, ...``. Byte Arrays: the single
    name of a one-name comment (unless it is time_s, record or element), else ``value``.
    """
    names = [n.strip() for n in comment] if comment is not None else []
    if kind == "array":
        name = names[0] if len(names) == 1 else ""
        return (name if name and name not in ("time_s", "record", "element") else "value",)
    if len(names) != spec.n_fields:
        names = []
    return _clean_names(names, spec.n_fields)
