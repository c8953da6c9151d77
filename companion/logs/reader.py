"""Reader of binary flight logs: whole file in, one numpy structured array per format out.

`read_log` and `read_log_bytes` are the entry points; what they return (`LogFile`, `Stream`,
...) and the layout of the arrays are in `companion.logs.streams`. This module owns the
meaning of the records: which definition applies to each record, whether its length fits its
format, Begin/End markers, and what becomes a stream. The other jobs of a read live beside it:
following the record chain (`companion.logs.framing`), what each definition requires of a
data record (`companion.logs.versions`), recovering from damage (`companion.logs.resync`) and
decoding a stream's records into arrays (`companion.logs.decode`).

How it stays fast: the framing hands over the offsets and headers of a stretch of records, and
everything here is done with numpy over all of them at once: while one set of definitions is
in force, one table indexed by a record's type and index bytes gives the length it needs and
its stream (`companion.logs.versions`). Every pass over all records costs about as much as reading the file once, so the
passes are few.

How it stays safe: every loop advances through the file, every allocation is proportional to
the file size, and anything the contract calls corruption is skipped up to the next offset
where a plausible record starts and recorded in `LogFile.damage` (the default), or, with
``strict=True``, raises `LogFormatError` with the byte offset.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from companion.logs.decode import array_stream, block_stream
from companion.logs.formats import FormatError, FormatSpec, parse_format
from companion.logs.framing import NO_OFFSETS, frame
from companion.logs.records import (
    BEGIN,
    COMMENT,
    DATA,
    END,
    HEADER_SIZE,
    NS_PER_S,
    TYPE_NAMES,
)
from companion.logs.resync import find_plausible, tail_damage
from companion.logs.streams import Damage, LogFile, LogFormatError, Marker, Stream, column_names
from companion.logs.versions import FEW, Requirements, Version, by_key, pairs_of

__all__ = ["read_log", "read_log_bytes"]

log = logging.getLogger(__name__)

_NO_BAD = np.zeros(0, dtype=bool)
_KEYED_MIN = 4096  # at least this many data records: checked through a table of 16-bit keys
_SALVAGE_WINDOW = 1024  # bytes parsed after a resynchronisation before validating (doubles)


class _Parser:
    def __init__(self, buf: bytes, path: str, salvage: bool, fast: bool = True) -> None:
        self.fast = fast  # False: the reference walk only (tests compare the two)
        self.buf = buf
        self.n = len(buf)
        self.arr = np.frombuffer(buf, dtype=np.uint8)
        self.path = path
        self.salvage = salvage
        self.versions: list[Version] = []
        self.current = np.full(256, -1, dtype=np.int64)  # version id in force per index
        self.markers: list[Marker] = []
        self.damage: list[Damage] = []
        self.warnings: list[str] = []
        self.truncated = 0
        self.record_count = 0
        # Kept data records: offsets, lengths, and their (version, kind) pairs (version * 2 + 1
        # for a Byte Array), one per record or as the positions of the records of each pair.
        self.chunks: list[
            tuple[np.ndarray, np.ndarray, np.ndarray | None, dict[int, np.ndarray | slice] | None]
        ] = []
        self._warned_columns: set[int] = set()
        self.requirements = Requirements()  # what a data record of each version needs

    # -- the main loop ---------------------------------------------------------------------

    def run(self) -> LogFile:
        pos = 0
        window = self.n  # unbounded until a resynchronisation
        while pos < self.n:
            stop = pos + window if window < self.n else self.n
            found, words, stop_off, reason = frame(self.buf, pos, stop, fast=self.fast)
            err = self._commit(found, words)
            if err is not None:
                pos = self._corrupt(*err)
                window = _SALVAGE_WINDOW
                continue
            if reason == "eof":
                break
            if reason == "window":
                pos = stop_off
                window *= 2
                continue
            if reason == "unknown":
                pos = self._corrupt(
                    stop_off,
                    "unknown_type",
                    f"unknown record type 0x{self.buf[stop_off]:02X}",
                )
                window = _SALVAGE_WINDOW
                continue
            tail = tail_damage(self.buf, stop_off, self._spec_of)
            if tail is None:
                self.truncated = self.n - stop_off
                msg = (
                    f"{self.path}: last record at byte offset {stop_off} is cut short "
                    f"({self.truncated} bytes dropped)"
                )
                self.warnings.append(msg)
                log.warning(msg)
                break
            pos = self._corrupt(stop_off, *tail)
            window = _SALVAGE_WINDOW
        return self._finish()

    def _corrupt(self, offset: int, kind: str, message: str) -> int:
        if not self.salvage:
            raise LogFormatError(self.path, offset, message, kind)
        nxt = find_plausible(self.buf, offset + 1, self.n, self._spec_of)
        self.damage.append(Damage(offset, kind, message, nxt - offset))
        log.warning(
            "%s: byte offset %d: %s; skipped %d bytes", self.path, offset, message, nxt - offset
        )
        return nxt

    # -- validation of a chunk of framed records -------------------------------------------

    def _time_at(self, off: int) -> int:
        sec = int.from_bytes(self.buf[off + 4 : off + 8], "little", signed=True)
        nsec = int.from_bytes(self.buf[off + 8 : off + 12], "little")
        return sec * NS_PER_S + nsec

    def _new_version(
        self, index: int, off: int, spec: FormatSpec | None, comment: tuple[str, ...] | None
    ) -> int:
        self.versions.append(Version(index, off, spec, comment))
        vid = len(self.versions) - 1
        self.current[index] = vid
        self.requirements.add(vid, spec)
        return vid

    def _control(self, off: int) -> tuple[str, str] | None:
        """Apply one control record; returns (kind, message) when it is corrupt."""
        buf = self.buf
        rtype, index = buf[off], buf[off + 1]
        length = buf[off + 2] | (buf[off + 3] << 8)
        if rtype in (BEGIN, END):
            if length:
                return "length_mismatch", f"{TYPE_NAMES[rtype]} with length {length} (must be 0)"
            kind = "begin" if rtype == BEGIN else "end"
            self.markers.append(Marker(kind, self._time_at(off), off))
            return None
        if index == 0:
            return "bad_definition", f"{TYPE_NAMES[rtype]} for format index 0 (must be 1..255)"
        body = buf[off + HEADER_SIZE : off + HEADER_SIZE + length].rstrip(b"\x00")
        cur = int(self.current[index])
        prev = self.versions[cur] if cur >= 0 else None
        if rtype == COMMENT:
            names = tuple(body.decode("utf-8", errors="replace").split(","))
            if prev is None or prev.comment != names:  # a repeat changes nothing
                self._new_version(index, off, prev.spec if prev else None, names)
            return None
        try:
            spec = parse_format(body.decode("latin-1"))
        except FormatError as exc:
            return "bad_definition", f"bad Format Definition for index {index}: {exc}"
        if prev is None or prev.spec != spec:
            self._new_version(index, off, spec, prev.comment if prev else None)
        return None

    def _commit(self, offs: np.ndarray, hdr: np.ndarray) -> tuple[int, str, str] | None:
        """Validate and keep framed records (offsets and headers) up to the first corrupt one
        (returned)."""
        if offs.size == 0:
            return None
        hdr = np.ascontiguousarray(hdr)  # as `frame` gives it: the views below need that
        types, idx = hdr.view(np.uint8)[0::4], hdr.view(np.uint8)[1::4]
        lens = hdr.view("<u2")[1::2]
        # The records framed are of the seven known types, and only the four control types
        # (Begin/End Data, Format Comment/Definition) have bit 2 set.
        ctrl = np.flatnonzero((hdr & 4) != 0)
        start_current = self.current.copy()
        n_versions0 = len(self.versions)
        n_markers0 = len(self.markers)
        err_pos = offs.size
        n_ctrl = ctrl.size
        err: tuple[str, str] | None = None
        ev_pos: list[int] = []
        for j, p in enumerate(ctrl.tolist()):
            before = len(self.versions)
            err = self._control(int(offs[p]))
            if err is not None:
                err_pos, n_ctrl = p, j
                break
            if len(self.versions) > before:
                ev_pos.append(p)
        # The data records before err_pos are usually one contiguous run (controls at the start
        # and the end): then slices (views) stand for gathers by their positions.
        run = _between(ctrl[:n_ctrl], err_pos)
        dsel: slice | np.ndarray
        if run is not None:
            dsel = slice(*run)
            n_data, first = run[1] - run[0], run[0]
        else:
            is_data = np.ones(err_pos, dtype=bool)
            is_data[ctrl[:n_ctrl]] = False
            dsel = np.flatnonzero(is_data)
            n_data, first = dsel.size, (int(dsel[0]) if dsel.size else 0)
        vid: np.ndarray | None = None
        groups: dict[int, np.ndarray | slice] | None = None
        need = pairs = NO_OFFSETS
        if n_data >= _KEYED_MIN and (not ev_pos or ev_pos[-1] < first):
            # One set of definitions for every data record: the records of each (type,
            # index) key a valid record can have are found with one compare each, and if
            # that is all of them, every one is valid; else tables over the key find the
            # first that is not.
            need16, pair16, valid = self.requirements.keyed(self.current)
            codes = hdr.view("<u2")[0::2][dsel]
            groups = by_key(hdr[dsel], codes, need16, pair16, valid)
            if groups is None:  # some record is corrupt (or too many formats): find it
                need, pairs = need16.take(codes), pair16.take(codes)
        elif n_data:
            data_pos = np.arange(dsel.start, dsel.stop) if isinstance(dsel, slice) else dsel
            vid = self._versions_of(idx, dsel, data_pos, ev_pos, start_current, n_versions0,
                                    offs.size)
            need, pairs = self.requirements.needs(vid, types[dsel])
        bad = need != lens[dsel] if groups is None else _NO_BAD
        if bad.any():
            bad &= need != -1  # -1: a Byte Array of a 1-byte format, any length
        if bad.any():
            k = int(np.argmax(bad))
            p = dsel.start + k if isinstance(dsel, slice) else int(dsel[k])
            index = int(idx[p])
            name = TYPE_NAMES[int(types[p])]
            v = int(vid[k]) if vid is not None else int(self.current[index])
            vspec = self.versions[v].spec if v >= 0 else None
            text = vspec.text if vspec is not None else ""
            if need[k] == -3:
                err = "undefined_index", f"{name} for format index {index}, which has no definition"
            elif types[p] == DATA:
                err = (
                    "length_mismatch",
                    f"Data Block of {int(lens[p])} bytes for format index {index}, "
                    f"whose format {text!r} needs {int(need[k])}",
                )
            else:
                err = (
                    "length_mismatch",
                    f"{name} for format index {index}, whose format {text!r} "
                    f"is not one 1-byte conversion",
                )
            err_pos = p
            keep = k  # the data records before the bad one
        else:
            keep = n_data
        if err_pos < offs.size:
            self._rollback(int(offs[err_pos]), start_current, n_versions0, n_markers0)
        if keep:
            if keep < n_data:
                dsel = slice(dsel.start, dsel.start + keep) if isinstance(dsel, slice) else dsel[:keep]
            self.chunks.append(
                (offs[dsel], lens[dsel], None if groups is not None else pairs[:keep], groups)
            )
        self.record_count += err_pos
        if err is not None:
            return int(offs[err_pos]), err[0], err[1]
        return None

    def _versions_of(
        self,
        idx: np.ndarray,
        dsel: slice | np.ndarray,
        data_pos: np.ndarray,
        ev_pos: list[int],
        start_current: np.ndarray,
        n_versions0: int,
        n_records: int,
    ) -> np.ndarray:
        """The version in force for each data record: the last event of its index before it."""
        d_idx = idx[dsel]
        first = int(data_pos[0])
        vid = (self.current if ev_pos and ev_pos[-1] < first else start_current)[d_idx]
        if ev_pos and ev_pos[-1] >= first:
            ev_p = np.asarray(ev_pos, dtype=np.int64)
            ev_vid = np.arange(n_versions0, len(self.versions), dtype=np.int64)
            ev_idx = idx[ev_p].astype(np.int64)
            span = n_records + 1
            ev_key = ev_idx * span + ev_p
            order = np.argsort(ev_key, kind="stable")
            ev_key, ev_vid, ev_idx = ev_key[order], ev_vid[order], ev_idx[order]
            j = np.searchsorted(ev_key, d_idx.astype(np.int64) * span + data_pos, side="right") - 1
            jc = np.clip(j, 0, None)
            hit = (j >= 0) & (ev_idx[jc] == d_idx)
            vid = np.where(hit, ev_vid[jc], vid)
        return vid

    def _rollback(
        self, offset: int, start_current: np.ndarray, n_versions0: int, n_markers0: int
    ) -> None:
        """Forget definitions and markers read at or after `offset` (past a corrupt record)."""
        while len(self.versions) > n_versions0 and self.versions[-1].offset >= offset:
            self.versions.pop()
        self.current = start_current
        for vid in range(n_versions0, len(self.versions)):
            self.current[self.versions[vid].index] = vid
        while len(self.markers) > n_markers0 and self.markers[-1].offset >= offset:
            self.markers.pop()

    # -- the definitions in force (what `companion.logs.resync` judges records by) -----------

    def _spec_of(self, index: int) -> FormatSpec | None:
        vid = int(self.current[index])
        return self.versions[vid].spec if vid >= 0 else None

    # -- building the arrays ---------------------------------------------------------------

    def _columns(self, vid: int, kind: str) -> tuple[str, ...]:
        v = self.versions[vid]
        assert v.spec is not None
        count = v.spec.n_fields
        if (
            kind == "block"
            and v.comment is not None
            and len(v.comment) != count
            and vid not in self._warned_columns
        ):
            self._warned_columns.add(vid)
            msg = (
                f"{self.path}: Format Comment of index {v.index} names {len(v.comment)} columns "
                f"for {count} fields; they are named c1..c{count} instead"
            )
            self.warnings.append(msg)
            log.warning(msg)
        return column_names(v.comment, v.spec, kind)

    def _grouped(
        self,
    ) -> tuple[np.ndarray, np.ndarray, dict[int, slice | np.ndarray], dict[int, int]]:
        """Offsets and lengths of the kept data records; the positions of the records of each
        (version, kind) pair present among them, in file order, and of its first record."""
        rows_of: dict[int, slice | np.ndarray] = {}
        first: dict[int, int] = {}
        groups = self.chunks[0][3] if len(self.chunks) == 1 else None
        if groups is not None:  # the usual case: one chunk, grouped by `by_key`
            offs, lens = self.chunks[0][0], self.chunks[0][1]
            for pv, found in groups.items():
                rows_of[pv] = found
                first[pv] = 0 if isinstance(found, slice) else int(found[0])
            return offs, lens, rows_of, first
        pairs = [pairs_of(c[0].size, c[2], c[3]) for c in self.chunks]
        if len(self.chunks) == 1:
            offs, lens, pair = self.chunks[0][0], self.chunks[0][1], pairs[0]
        elif self.chunks:
            offs = np.concatenate([c[0] for c in self.chunks])
            lens = np.concatenate([c[1] for c in self.chunks])
            pair = np.concatenate(pairs)
        else:
            offs = lens = pair = np.zeros(0, dtype=np.int64)
        present = np.flatnonzero(np.bincount(pair)) if pair.size else NO_OFFSETS
        if present.size == 1:
            rows_of[int(present[0])], first[int(present[0])] = slice(None), 0
        elif present.size <= FEW:  # a handful of formats; no sort
            for pv in present.tolist():
                rows_of[pv] = found = np.flatnonzero(pair == pv)
                first[pv] = int(found[0])
        else:
            order = np.argsort(pair, kind="stable")
            ranked = pair[order]
            lo = np.searchsorted(ranked, present, side="left").tolist()
            hi = np.searchsorted(ranked, present, side="right").tolist()
            for pv, a, b in zip(present.tolist(), lo, hi, strict=True):
                rows_of[pv] = order[a:b]
                first[pv] = int(order[a])
        return offs, lens, rows_of, first

    def _finish(self) -> LogFile:
        streams: list[Stream] = []
        offs, lens, rows_of, first = self._grouped()
        # Streams in order of their first record; (version, kind) pairs map onto them.
        key_of: dict[tuple[int, str, str, tuple[str, ...]], int] = {}
        stream_keys: list[tuple[int, str, tuple[str, ...], int]] = []
        members: list[list[int]] = []
        for pv in sorted(rows_of, key=first.__getitem__):
            vid, kind = pv // 2, ("array" if pv % 2 else "block")
            spec = self.versions[vid].spec
            assert spec is not None
            columns = self._columns(vid, kind)
            key = (self.versions[vid].index, kind, spec.text, columns)
            if key not in key_of:
                key_of[key] = len(stream_keys)
                stream_keys.append((self.versions[vid].index, kind, columns, vid))
                members.append([])
            members[key_of[key]].append(pv)
        numbers: dict[int, int] = {}
        for (index, kind, columns, vid), pvs in zip(stream_keys, members, strict=True):
            rows: slice | np.ndarray = rows_of[pvs[0]]
            if len(pvs) > 1:  # one layout under several versions (e.g. a repeated comment)
                rows = np.sort(np.concatenate([rows_of[pv] for pv in pvs]))
            numbers[index] = numbers.get(index, 0) + 1
            spec = self.versions[vid].spec
            assert spec is not None
            at = self.versions[vid].offset
            number = numbers[index]
            if kind == "block":
                streams.append(block_stream(self.arr, index, spec, columns, number, at, offs[rows]))
            else:
                streams.append(
                    array_stream(self.arr, index, spec, columns, number, at, offs[rows], lens[rows])
                )
        # Formats that were defined but never used still show up, with no records.
        used = {s.index for s in streams}
        for index in range(1, 256):
            vid = int(self.current[index])
            if index in used or vid < 0:
                continue
            spec = self.versions[vid].spec
            if spec is None:
                continue
            empty = np.zeros(0, dtype=np.int64)
            columns = self._columns(vid, "block")
            at = self.versions[vid].offset
            streams.append(block_stream(self.arr, index, spec, columns, 1, at, empty))
        streams.sort(key=lambda s: (s.index, s.number))
        if not self.markers or self.markers[-1].kind != "end":
            self.warnings.append(f"{self.path}: not closed cleanly (no End Data at the end)")
        return LogFile(
            path=self.path,
            size_bytes=self.n,
            streams=streams,
            markers=self.markers,
            damage=self.damage,
            truncated_bytes=self.truncated,
            record_count=self.record_count,
            warnings=self.warnings,
        )


def _between(ctrl: np.ndarray, end: int) -> tuple[int, int] | None:
    """(a, b) when the positions of [0, end) not in `ctrl` (increasing, all below end) are the
    run [a, b), else None."""
    k = ctrl.size
    if not k:
        return 0, end
    lead = int(np.count_nonzero(ctrl == np.arange(k)))  # ctrl[j] - j never decreases
    rest = k - lead
    if rest and int(ctrl[lead]) != end - rest:
        return None
    return lead, end - rest


def _skips_damage(salvage: bool | None, strict: bool) -> bool:
    """Reading what is whole is the default (damage skipped and listed in `LogFile.damage`);
    `strict=True` refuses damage, and an explicit `salvage` from older callers still decides."""
    return (not strict) if salvage is None else salvage


def read_log_bytes(data: bytes, *, name: str = "<bytes>", salvage: bool | None = None,
                   strict: bool = False) -> LogFile:
    """Read a binary log held in memory; `name` is used in messages. Damage is skipped and
    reported unless `strict` (see `read_log`)."""
    return _Parser(bytes(data), name, _skips_damage(salvage, strict)).run()


def read_log(path: str | os.PathLike[str], *, salvage: bool | None = None,
             strict: bool = False) -> LogFile:
    """Read a binary log file: what is whole is read, damage in the middle is skipped up to the
    next plausible record and listed in `LogFile.damage` with its byte offset, and a cut-short
    last record is dropped with a warning (how a log ends when the power goes).

    `strict=True` raises LogFormatError (with the file name and byte offset) on any damage
    instead; `salvage=False` means the same, `salvage=True` the default, for older callers.
    """
    p = Path(path)
    return read_log_bytes(p.read_bytes(), name=str(p), salvage=_skips_damage(salvage, strict))
