"""Definition versions of a binary flight log and what they require of its data records.

Every Format Definition or Comment that changes an index starts a new *version* (`Version`);
each data record belongs to the version of its index in force where it stands, and to a
*pair* (version * 2, + 1 for a Byte Array) that decides its stream. `Requirements` keeps, per
version, the length a Data Block needs and whether Byte Arrays are allowed, as numpy tables,
so that the reader (`companion.logs.reader`) checks and groups every data record of a stretch
at once: by its version (`Requirements.needs`) or, while one set of definitions is in force,
by its type and index bytes alone (`Requirements.keyed`, `by_key`). It is separate from the
reader's loop because these tables are the one place where a format's record length is
turned into a check, and they hold no state of the file being read.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from companion.logs.formats import FormatSpec
from companion.logs.records import ARRAY, ARRAY_ALT, DATA

__all__ = ["FEW", "Requirements", "Version", "by_key", "pairs_of"]

FEW = 16  # at most this many formats/streams: group records by one pass per format


@dataclass
class Version:
    """The definition state of one index from one FD/FC record on."""

    index: int
    offset: int
    spec: FormatSpec | None
    comment: tuple[str, ...] | None


class Requirements:
    """Per version id: the data size its format needs (-1: a comment only, no format yet) and
    whether it can hold Byte Arrays (one 1-byte conversion)."""

    def __init__(self) -> None:
        self.size = np.full(16, -1, dtype=np.int64)
        self.bytes_ok = np.zeros(16, dtype=bool)

    def add(self, vid: int, spec: FormatSpec | None) -> None:
        """Version `vid` (the next one) has format `spec` (None: a comment only)."""
        if vid >= self.size.size:
            self.size = np.concatenate([self.size, np.full_like(self.size, -1)])
            self.bytes_ok = np.concatenate([self.bytes_ok, np.zeros_like(self.bytes_ok)])
        self.size[vid] = spec.size if spec is not None else -1
        self.bytes_ok[vid] = bool(spec is not None and spec.byte_array_ok)

    def keyed(self, current: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[int]]:
        """Per (type | index << 8) key of a data record, with the versions `current` in force:
        the length it needs (see `needs`) and its pair (version * 2 + 1 for a Byte Array);
        and the keys a valid record can have."""
        have = current >= 0
        v = np.where(have, current, 0)
        size = np.where(have, self.size[v], -1)
        block = np.where(size >= 0, size, -3)
        array = np.where(size >= 0, np.where(self.bytes_ok[v], -1, -2), -3)
        need16 = np.full(1 << 16, -3, dtype=np.int32)
        pair16 = np.zeros(1 << 16, dtype=np.int32)
        keys = np.arange(256, dtype=np.int64) << 8
        need16[keys + DATA] = block
        pair16[keys + DATA] = v * 2
        for t in (ARRAY, ARRAY_ALT):
            need16[keys + t] = array
            pair16[keys + t] = v * 2 + 1
        valid = (keys[block >= 0] + DATA).tolist()
        for t in (ARRAY, ARRAY_ALT):
            valid += (keys[array == -1] + t).tolist()
        return need16, pair16, valid

    def needs(self, vid: np.ndarray, d_types: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per data record of version `vid`: the length its (version, kind) requires (-1 any: a
        Byte Array of a 1-byte format; -2 none: a Byte Array of another format; -3 no
        definition) and its pair (version * 2 + 1 for a Byte Array)."""
        sizes = self.size
        known_size = sizes >= 0
        lut = np.full(2 * sizes.size + 2, -3, dtype=np.int64)
        lut[2::2] = np.where(known_size, sizes, -3)
        lut[3::2] = np.where(known_size, np.where(self.bytes_ok, -1, -2), -3)
        pair = vid * 2 + (d_types != DATA)
        return lut[pair + 2], pair


def by_key(
    words: np.ndarray, codes: np.ndarray, need16: np.ndarray, pair16: np.ndarray,
    valid: list[int],
) -> dict[int, np.ndarray | slice] | None:
    """The positions of the records of each (version, kind) pair, by the keys a valid record
    can have (see `Requirements.keyed`): a Data Block's whole header is known, a Byte Array's type
    and index. None when some record has none of them (it is corrupt) or the keys are too many
    for a pass each."""
    if len(valid) > FEW:
        return None
    groups: dict[int, np.ndarray | slice] = {}
    total = 0
    for k16 in valid:
        need = int(need16[k16])
        same = words == (k16 | need << 16) if need >= 0 else codes == k16
        if len(valid) == 1:  # every record has the key, or some record is corrupt
            return {int(pair16[k16]): slice(None)} if same.all() else None
        found = np.flatnonzero(same)
        if not found.size:
            continue
        total += found.size
        pv = int(pair16[k16])
        if pv in groups:  # a Byte Array under both type codes
            found = np.sort(np.concatenate([groups[pv], found]))
        groups[pv] = found
    return groups if total == words.size else None


def pairs_of(
    count: int, pairs: np.ndarray | None, groups: dict[int, np.ndarray | slice] | None
) -> np.ndarray:
    """The pair of each of the `count` records of a chunk (see `companion.logs.reader._Parser.chunks`): `pairs`, or
    the pairs `groups` (`by_key`) stands for."""
    if pairs is not None or groups is None:
        return pairs if pairs is not None else np.zeros(count, dtype=np.int64)
    out = np.empty(count, dtype=np.int64)
    for pv, rows in groups.items():
        out[rows] = pv
    return out
