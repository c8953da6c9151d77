"""A flight directory as one uncompressed POSIX (ustar) archive built on the fly; unpacking.

Why an archive: the ground stations' log download (MAVLink LOG_* messages) moves one file per
log entry; serving a whole flight (binary logs, run.json, summary.json, tlogs, CSVs) as one
tar gives a researcher the complete flight in one download, readable by Python's `tarfile` and
GNU tar without any tool of ours.

`FlightArchive.snapshot` fixes the list of files and their sizes when it is taken: the logs of
a flight being recorded keep growing, and a download must see the same bytes however often and
in whatever order its ranges are asked for, so each file contributes its first `size` bytes as
of the snapshot. Nothing is copied: `FlightArchive.read` builds any byte range from the headers
kept in memory and the needed pieces of the files. The archive is deterministic (sorted names,
uid/gid 0, no user or group names, fixed modes), so two snapshots of an unchanged flight are
byte-identical.

Clients save the download under names like ``log_3_2024-5-1-10-2-33.bin`` or ``.ulg``, so
`is_archive` recognises an archive by its content and `unpack_flight` turns it back into a
flight directory for the ``companion logs`` tools.
"""

from __future__ import annotations

import bisect
import logging
import os
import shutil
import stat
import tarfile
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "ArchiveError",
    "FlightArchive",
    "Member",
    "Unpacked",
    "is_archive",
    "unpack",
    "unpack_flight",
]

log = logging.getLogger(__name__)

BLOCK = 512
_END_BLOCKS = 2  # two zero blocks end a POSIX archive
_NAME_LEN = 100
_PREFIX_LEN = 155
_FILE_MODE = 0o644
_DIR_MODE = 0o755
_MAX_SIZE = 8**11 - 1  # 11 octal digits in the ustar size field (8 GiB - 1)
_MAX_MTIME = 8**11 - 1
_MAGIC_OFFSET = 257
_MAGICS = (b"ustar\x00", b"ustar ")  # POSIX ustar/pax, and GNU tar's "ustar  \0"
_COMPARE_CHUNK = 1 << 20


class ArchiveError(ValueError):
    """A flight archive that cannot be built, read or unpacked; names the file (and the byte
    offset in the archive when one applies), like `LogFormatError` does for logs."""

    def __init__(self, path: str | os.PathLike[str], message: str,
                 offset: int | None = None) -> None:
        self.path = str(path)
        self.offset = offset
        self.reason = message
        where = f"{self.path}: byte offset {offset}" if offset is not None else self.path
        super().__init__(f"{where}: {message}")


@dataclass(frozen=True)
class Member:
    """One file or directory of a snapshot, as it stands in the archive."""

    name: str  # "<flight>/<relative path>", directories end with "/"
    path: Path  # on disk
    is_dir: bool
    size: int  # bytes of the file in the archive (0 for a directory)
    mtime_s: int  # integer modification time written in the header
    header_offset: int
    data_offset: int
    # what the file was at the snapshot: a read checks that it is still the same file
    dev: int
    ino: int
    mtime_ns: int


@dataclass(frozen=True)
class _Piece:
    start: int
    length: int
    blob: bytes | None  # header bytes; None with member None: zero padding
    member: Member | None  # file data


def _octal(value: int, width: int) -> bytes:
    """A ustar numeric field: zero-padded octal digits and a NUL, `width` bytes in all."""
    return b"%0*o\x00" % (width - 1, value)


def _split_name(name: bytes) -> tuple[bytes, bytes]:
    """(prefix, name) of a ustar header; a name over 100 bytes is split at a '/'."""
    if len(name) <= _NAME_LEN:
        return b"", name
    body = name.rstrip(b"/")
    for i, ch in enumerate(body):
        if ch == ord("/") and i <= _PREFIX_LEN and len(name) - i - 1 <= _NAME_LEN:
            return name[:i], name[i + 1:]
    raise ValueError(f"the name is {len(name)} bytes: ustar stores at most 100 bytes after a "
                     "directory prefix of at most 155")


def _header(name: bytes, *, is_dir: bool, size: int, mtime_s: int) -> bytes:
    prefix, short = _split_name(name)
    h = bytearray(BLOCK)
    h[0:len(short)] = short
    h[100:108] = _octal(_DIR_MODE if is_dir else _FILE_MODE, 8)
    h[108:116] = _octal(0, 8)  # uid
    h[116:124] = _octal(0, 8)  # gid
    h[124:136] = _octal(size, 12)
    h[136:148] = _octal(mtime_s, 12)
    h[148:156] = b" " * 8  # checksum counted as spaces
    h[156] = ord("5") if is_dir else ord("0")
    h[257:263] = b"ustar\x00"
    h[263:265] = b"00"
    h[329:337] = _octal(0, 8)  # devmajor
    h[337:345] = _octal(0, 8)  # devminor
    h[345:345 + len(prefix)] = prefix
    h[148:156] = b"%06o\x00 " % sum(h)
    return bytes(h)


class FlightArchive:
    """A read-only, deterministic ustar view of a flight directory as it was at `snapshot`."""

    def __init__(self, flight_dir: Path, name: str, members: Sequence[Member],
                 pieces: Sequence[_Piece], size: int) -> None:
        """Use `snapshot`; this only stores what it computed."""
        self.flight_dir = flight_dir
        self.name = name
        self.members = tuple(members)
        self._pieces = tuple(pieces)
        self._starts = [p.start for p in pieces]
        self.size = size
        self.mtime_s = max((m.mtime_s for m in members), default=0)
        """Latest modification time of the flight's files and directories (s since the epoch)."""

    def __repr__(self) -> str:
        return (f"FlightArchive({str(self.flight_dir)!r}, {len(self.members)} members, "
                f"{self.size} B)")

    @property
    def first_mtime_s(self) -> int:
        """Earliest modification time of its files: when the flight started, at the latest."""
        return min((m.mtime_s for m in self.members if not m.is_dir), default=self.mtime_s)

    @classmethod
    def snapshot(cls, flight_dir: str | os.PathLike[str]) -> FlightArchive:
        """The archive of the regular files under `flight_dir` (recursive, sorted), each with
        its size now. Hidden files (atomic-write temporaries), symbolic links and special files
        are left out: they are not flight data, and a link could reach files outside the flight.

        Raises ArchiveError when `flight_dir` is not a directory or a name or size does not fit
        in a ustar header.
        """
        root = Path(flight_dir)
        if not root.is_dir():
            raise ArchiveError(root, "not a flight directory")
        name = root.resolve().name
        if not name:
            raise ArchiveError(root, "a flight directory needs a name")
        entries: list[tuple[str, Path, os.stat_result]] = []
        try:
            entries.append((name + "/", root, root.stat()))
        except OSError as exc:
            raise ArchiveError(root, f"cannot be read: {exc.strerror or exc}") from exc
        _walk(root, name + "/", entries, is_root=True)

        members: list[Member] = []
        pieces: list[_Piece] = []
        offset = 0
        for member_name, path, st in entries:
            is_dir = stat.S_ISDIR(st.st_mode)
            size = 0 if is_dir else st.st_size
            if size > _MAX_SIZE:
                raise ArchiveError(path, f"{size} bytes: too large for a ustar archive member")
            mtime_s = min(max(int(st.st_mtime), 0), _MAX_MTIME)
            try:
                header = _header(os.fsencode(member_name), is_dir=is_dir, size=size,
                                 mtime_s=mtime_s)
            except ValueError as exc:
                raise ArchiveError(path, str(exc)) from exc
            member = Member(member_name, path, is_dir, size, mtime_s, offset, offset + BLOCK,
                            st.st_dev, st.st_ino, st.st_mtime_ns)
            members.append(member)
            pieces.append(_Piece(offset, BLOCK, header, None))
            offset += BLOCK
            if size:
                pieces.append(_Piece(offset, size, None, member))
                offset += size
                pad = -size % BLOCK
                if pad:
                    pieces.append(_Piece(offset, pad, None, None))
                    offset += pad
        pieces.append(_Piece(offset, _END_BLOCKS * BLOCK, None, None))
        offset += _END_BLOCKS * BLOCK
        return cls(root, name, members, pieces, offset)

    def read(self, offset: int, n: int) -> bytes:
        """`n` bytes of the archive from `offset` (fewer at the end, none past it).

        Reads only the pieces of files the range covers, and gives the same bytes every time:
        a file that since shrank, vanished, was replaced or was rewritten in place raises
        ArchiveError naming it (the bytes the snapshot promised no longer exist).
        """
        if offset < 0 or n < 0:
            raise ValueError(f"negative offset or length: {offset}, {n}")
        stop = min(offset + n, self.size)
        if offset >= stop:
            return b""
        out = bytearray()
        i = bisect.bisect_right(self._starts, offset) - 1
        pos = offset
        while pos < stop:
            piece = self._pieces[i]
            begin = pos - piece.start
            length = min(piece.start + piece.length, stop) - pos
            if piece.blob is not None:
                out += piece.blob[begin:begin + length]
            elif piece.member is not None:
                out += _read_member(piece.member, begin, length)
            else:
                out += bytes(length)
            pos += length
            i += 1
        return bytes(out)

    def write_to(self, dest: str | os.PathLike[str], chunk_bytes: int = 1 << 20) -> Path:
        """Write the whole archive to `dest` (what a client's download reassembles)."""
        path = Path(dest)
        with open(path, "wb") as f:
            for start in range(0, self.size, chunk_bytes):
                f.write(self.read(start, chunk_bytes))
        return path


def _walk(directory: Path, prefix: str, out: list[tuple[str, Path, os.stat_result]],
          *, is_root: bool = False) -> None:
    """Depth-first, names sorted: each directory's entry comes before its contents."""
    try:
        with os.scandir(directory) as it:
            entries = sorted(it, key=lambda e: e.name)
    except OSError as exc:
        if is_root:
            raise ArchiveError(directory, f"cannot be listed: {exc.strerror or exc}") from exc
        log.warning("flight archive: leaving out %s: %s", directory, exc.strerror or exc)
        return
    for e in entries:
        if e.name.startswith("."):
            continue
        try:
            if e.is_symlink():
                log.debug("flight archive: leaving out symbolic link %s", e.path)
                continue
            st = e.stat(follow_symlinks=False)
        except FileNotFoundError:  # removed while listing: not part of the snapshot
            continue
        path = Path(e.path)
        if stat.S_ISDIR(st.st_mode):
            out.append((f"{prefix}{e.name}/", path, st))
            _walk(path, f"{prefix}{e.name}/", out)
        elif stat.S_ISREG(st.st_mode):
            out.append((prefix + e.name, path, st))


def _read_member(m: Member, begin: int, length: int) -> bytes:
    try:
        f = open(m.path, "rb")  # noqa: SIM115 - closed below; the error message needs the open
    except FileNotFoundError as exc:
        raise ArchiveError(m.path, "vanished since the flight's snapshot") from exc
    except OSError as exc:
        raise ArchiveError(m.path, f"cannot be read: {exc.strerror or exc}") from exc
    with f:
        st = os.fstat(f.fileno())
        if (st.st_dev, st.st_ino) != (m.dev, m.ino):
            raise ArchiveError(m.path, "was replaced since the flight's snapshot")
        if st.st_size < m.size:
            raise ArchiveError(m.path, f"shrank from {m.size} to {st.st_size} bytes since the "
                                       "flight's snapshot")
        if st.st_size == m.size and st.st_mtime_ns != m.mtime_ns:
            raise ArchiveError(m.path, "was rewritten since the flight's snapshot")
        f.seek(begin)
        data = f.read(length)
    if len(data) != length:
        raise ArchiveError(m.path, f"shrank below {begin + length} bytes since the flight's "
                                   "snapshot")
    return data


# ----------------------------------------------------------------------------- unpacking
def is_archive(path: str | os.PathLike[str]) -> bool:
    """True when `path` is a file that starts like a tar archive (ustar, pax or GNU magic),
    whatever its name: ground stations save the download as ``.bin``, ``.ulg`` or else."""
    try:
        with open(path, "rb") as f:
            head = f.read(BLOCK)
    except OSError:
        return False
    return head[_MAGIC_OFFSET:_MAGIC_OFFSET + 6] in _MAGICS


@dataclass(frozen=True)
class Unpacked:
    """Where `unpack` put a flight, and whether it found it already unpacked."""

    flight_dir: Path
    reused: bool


def unpack_flight(path: str | os.PathLike[str],
                  dest: str | os.PathLike[str] | None = None) -> Path:
    """Unpack the flight archive `path` into `dest` (default: ``<path.name>.flight/`` next to
    it) and return the flight directory inside; see `unpack`."""
    return unpack(path, dest).flight_dir


def unpack(path: str | os.PathLike[str], dest: str | os.PathLike[str] | None = None) -> Unpacked:
    """Unpack the flight archive `path` once.

    The whole archive is checked before anything is written: a truncated or corrupt one raises
    ArchiveError with the file and the byte offset, and so does a member that is absolute,
    leads outside with ``..``, is not a file or directory, or is not inside the one flight
    directory an archive holds. Extraction uses tarfile's "data" filter, into a temporary
    directory renamed into place, so an interrupted unpack leaves no half flight behind. When
    the flight directory already exists and holds every member with the same bytes (other
    files, such as CSVs converted from it, may be there too), it is reused; when it differs
    it is left alone and ArchiveError says so.
    """
    src = Path(path)
    container = Path(dest) if dest is not None else src.with_name(src.name + ".flight")
    try:
        size = src.stat().st_size
        tf = tarfile.open(src, "r:")
    except tarfile.TarError as exc:
        raise ArchiveError(src, f"not a readable tar archive: {exc}", 0) from exc
    except OSError as exc:
        raise ArchiveError(src, f"cannot be read: {exc.strerror or exc}") from exc
    with tf:
        members = _scan(tf, src, size)
        top = _flight_name(src, members)
        flight = container / top
        if flight.exists() or flight.is_symlink():
            differs = _difference(tf, members, container)
            if differs is None:
                log.info("%s: already unpacked in %s", src, flight)
                return Unpacked(flight, reused=True)
            raise ArchiveError(src, f"{flight} exists and differs from the archive ({differs}); "
                                    "remove it to unpack the archive again")
        container.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".unpacking-", dir=container))
        try:
            try:
                tf.extractall(tmp, members=members, filter="data")
            except tarfile.TarError as exc:
                raise ArchiveError(src, f"cannot be unpacked: {exc}") from exc
            os.rename(tmp / top, flight)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    log.info("%s: unpacked into %s", src, flight)
    return Unpacked(flight, reused=False)


def _scan(tf: tarfile.TarFile, src: Path, size: int) -> list[tarfile.TarInfo]:
    """Every member, after checking that each one's data and the end-of-archive marker are
    all there and that nothing but zeros follows the marker.

    tarfile alone stops quietly at a damaged header or a zero block (what a download with a
    hole leaves where a header was), which would unpack part of a flight without a word.
    """
    members: list[tarfile.TarInfo] = []
    while True:
        at = tf.offset
        try:
            m = tf.next()
        except tarfile.TarError as exc:
            raise ArchiveError(src, f"corrupt or truncated archive: {exc}", at) from exc
        if m is None:
            break
        if m.offset_data + m.size > size:
            raise ArchiveError(src, f"truncated: member {m.name!r} needs {m.size} bytes from byte "
                                    f"offset {m.offset_data}, the file ends before", size)
        members.append(m)
    end = tf.offset
    with open(src, "rb") as f:
        f.seek(end)
        marker = f.read(BLOCK)
        if marker.strip(b"\x00"):
            kind = "truncated" if len(marker) < BLOCK else "corrupt (bad checksum)"
            raise ArchiveError(src, f"{kind} tar header", end)
        if len(marker) < BLOCK:
            raise ArchiveError(src, "truncated: the end-of-archive marker is missing", size)
        pos = end + BLOCK
        while chunk := f.read(_COMPARE_CHUNK):
            stripped = chunk.lstrip(b"\x00")
            if stripped:
                at = pos + len(chunk) - len(stripped)
                raise ArchiveError(src, f"data after a zero block at byte offset {end}: the "
                                        "archive has a hole (an incomplete download?)", at)
            pos += len(chunk)
    if not members:
        raise ArchiveError(src, "the archive is empty", 0)
    return members


def _flight_name(src: Path, members: Sequence[tarfile.TarInfo]) -> str:
    """The one top-level directory every member is in, after the safety checks."""
    tops: set[str] = set()
    for m in members:
        parts = m.name.split("/")
        if m.name.startswith("/") or ".." in parts:
            raise ArchiveError(src, f"member {m.name!r} is absolute or leads outside with '..'; "
                                    "refusing to unpack", m.offset)
        if not (m.isfile() or m.isdir()):
            raise ArchiveError(src, f"member {m.name!r} is not a file or a directory; a flight "
                                    "archive holds nothing else", m.offset)
        parts = [p for p in parts if p not in ("", ".")]
        if not parts or (len(parts) == 1 and not m.isdir()):
            raise ArchiveError(src, f"member {m.name!r} is not inside a flight directory",
                               m.offset)
        tops.add(parts[0])
    if len(tops) != 1:
        raise ArchiveError(src, f"a flight archive holds one flight directory, this one "
                                f"{len(tops)}: {', '.join(sorted(tops))}")
    return tops.pop()


def _difference(tf: tarfile.TarFile, members: Sequence[tarfile.TarInfo],
                container: Path) -> str | None:
    """None when every member is on disk under `container` with the same bytes, else the
    first difference."""
    for m in members:
        target = container / m.name
        if m.isdir():
            if not target.is_dir() or target.is_symlink():
                return f"{m.name} is not a directory there"
            continue
        if target.is_symlink() or not target.is_file():
            return f"{m.name} is missing"
        if target.stat().st_size != m.size:
            return f"{m.name} has another size"
        src = tf.extractfile(m)
        if src is None:  # pragma: no cover - regular members always have a file object
            return f"{m.name} cannot be read from the archive"
        with src, open(target, "rb") as have:
            while True:
                want = src.read(_COMPARE_CHUNK)
                if want != have.read(len(want)):
                    return f"{m.name} has other contents"
                if not want:
                    break
    return None
