"""MAVLink FTP server over one directory tree: request payloads in, reply payloads out.

`FtpServer.handle` takes the `payload` of a FILE_TRANSFER_PROTOCOL request and yields complete
251-byte reply payloads (or None: "worked, no reply yet", so the caller can bound the work done
per step). It opens no socket and sends nothing; the caller wraps, paces and may abandon replies.

What the clients need, beyond https://mavlink.io/en/services/ftp.html:
- Sessions are chosen by the client. MAVProxy gives every operation its own session byte and
  routes replies by it; MAVSDK always sends 0 and ignores the session an ACK names. So an
  Open*/CreateFile request gets the session it asked for, and a reopen of a session still open
  replaces it (a retry whose ACK was lost must not fail). Every reply echoes the request's session
  and offset (MAVProxy finds an acknowledged write block by the offset of the ACK).
- Re-sent requests: the last few answers of each session are kept for `session_timeout_s`; a
  request equal to one of them (same seq, opcode, size, offset, data) gets the same replies again
  and is not re-executed, so a duplicated CreateFile cannot truncate a file already written.
  Bursts are read-only and are simply read again.
- A burst runs to the end of the file, `burst_complete` on its last packet (MAVSDK ends on
  offset + size >= the size the open announced; MAVProxy on a short packet or on a NAK EOF, so a
  burst asked to start at the end gets NAK EOF). Packets carry seq + 1, seq + 2, ... like PX4,
  ArduPilot and MAVSDK's server. A session reads its file as long as it was when opened, so a log
  still being recorded is served up to the size the OpenFileRO ACK announced.
- ListDirectoryWithTime (opcode 16) is served as well: MAVProxy and MAVSDK try it first.
- CalcFileCRC32 is MAVLink's CRC32 (reflected 0x04C11DB7 from 0 and no final inversion), which
  MAVSDK and MAVProxy's `crclocal` compute; it is not zlib.crc32 (see `mavlink_crc32`).
Sessions and remembered answers are keyed by the session byte alone, not by link: give each
client link its own FtpServer. Idle sessions are closed when the next request arrives (`close`
closes all). Not thread-safe: one thread calls `handle` and steps the iterators.

Size: about 650 lines: one protocol with seventeen opcodes, the confinement to the root and the
memory of answers, which only make sense together; `reply_to` at the end is the service-less answer
the dispatcher uses until it is rewired to a FtpServer.
"""

from __future__ import annotations

import errno
import itertools
import logging
import os
import stat
import struct
import time
import zlib
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

from gcs_bridge.dialect import mavlink

log = logging.getLogger(__name__)

HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst, pad, offset
PAYLOAD_LEN = 251
DATA_LEN = PAYLOAD_LEN - HEADER.size  # 239: the most data one payload carries
_U32 = struct.Struct("<I")

OP_NONE = mavlink.MAV_FTP_OPCODE_NONE
OP_TERMINATE_SESSION = mavlink.MAV_FTP_OPCODE_TERMINATESESSION
OP_RESET_SESSIONS = mavlink.MAV_FTP_OPCODE_RESETSESSION
OP_LIST_DIRECTORY = mavlink.MAV_FTP_OPCODE_LISTDIRECTORY
OP_OPEN_FILE_RO = mavlink.MAV_FTP_OPCODE_OPENFILERO
OP_READ_FILE = mavlink.MAV_FTP_OPCODE_READFILE
OP_CREATE_FILE = mavlink.MAV_FTP_OPCODE_CREATEFILE
OP_WRITE_FILE = mavlink.MAV_FTP_OPCODE_WRITEFILE
OP_REMOVE_FILE = mavlink.MAV_FTP_OPCODE_REMOVEFILE
OP_CREATE_DIRECTORY = mavlink.MAV_FTP_OPCODE_CREATEDIRECTORY
OP_REMOVE_DIRECTORY = mavlink.MAV_FTP_OPCODE_REMOVEDIRECTORY
OP_OPEN_FILE_WO = mavlink.MAV_FTP_OPCODE_OPENFILEWO
OP_TRUNCATE_FILE = mavlink.MAV_FTP_OPCODE_TRUNCATEFILE
OP_RENAME = mavlink.MAV_FTP_OPCODE_RENAME
OP_CALC_FILE_CRC32 = mavlink.MAV_FTP_OPCODE_CALCFILECRC
OP_BURST_READ_FILE = mavlink.MAV_FTP_OPCODE_BURSTREADFILE
OP_LIST_DIRECTORY_WITH_TIME = 16  # in the FTP spec, newer than pymavlink's MAV_FTP_OPCODE
OP_ACK = mavlink.MAV_FTP_OPCODE_ACK
OP_NAK = mavlink.MAV_FTP_OPCODE_NAK

ERR_FAIL = mavlink.MAV_FTP_ERR_FAIL
ERR_FAILERRNO = mavlink.MAV_FTP_ERR_FAILERRNO
ERR_INVALIDDATASIZE = mavlink.MAV_FTP_ERR_INVALIDDATASIZE
ERR_INVALIDSESSION = mavlink.MAV_FTP_ERR_INVALIDSESSION
ERR_NOSESSIONSAVAILABLE = mavlink.MAV_FTP_ERR_NOSESSIONSAVAILABLE
ERR_EOF = mavlink.MAV_FTP_ERR_EOF
ERR_UNKNOWNCOMMAND = mavlink.MAV_FTP_ERR_UNKNOWNCOMMAND
ERR_FILEEXISTS = mavlink.MAV_FTP_ERR_FILEEXISTS
ERR_FILEPROTECTED = mavlink.MAV_FTP_ERR_FILEPROTECTED
ERR_FILENOTFOUND = mavlink.MAV_FTP_ERR_FILENOTFOUND

_CRC_PIECE_BYTES = 64 * 1024  # CRC work between two yields
_LIST_PIECE_ENTRIES = 64  # directory entries looked at between two yields
_REPLAY_DEPTH = 16  # answers remembered per session for re-sent requests
_MAX_FILE_BYTES = 0xFFFFFFFF  # sizes and offsets are uint32 on the wire
_MASK32 = 0xFFFFFFFF


def mavlink_crc32(data: bytes, crc: int = 0) -> int:
    """MAVLink's CRC32 of `data`, continuing from `crc` (0 to start).

    MAVLink FTP uses the reflected CRC32 of 0x04C11DB7 started from 0 and without the final
    inversion (mavlink.io guide/crc, MAVSDK crc32.cpp, ArduPilot crc_crc32). zlib runs the same
    table but inverts on the way in and out, so handing it the inverted state cancels both.
    """
    return zlib.crc32(data, crc ^ _MASK32) ^ _MASK32


class _Nak(Exception):
    """Ends a request with a NAK: `code` is a MAV_FTP_ERR, `errno_` is sent only with FAILERRNO."""

    def __init__(self, code: int, errno_: int = 0) -> None:
        super().__init__(code, errno_)
        self.code = code
        self.errno_ = errno_


def _nak_for(exc: OSError) -> _Nak:
    """The NAK for a file-system error: the two the spec names, else FAILERRNO with the errno
    (MAVSDK turns FAILERRNO+ENOENT into "does not exist" as well; ArduPilot maps the same two)."""
    if isinstance(exc, FileNotFoundError):
        return _Nak(ERR_FILENOTFOUND)
    if isinstance(exc, FileExistsError):
        return _Nak(ERR_FILEEXISTS)
    if exc.errno:
        return _Nak(ERR_FAILERRNO, exc.errno & 0xFF)
    return _Nak(ERR_FAIL)


@dataclass(frozen=True)
class _Request:
    seq: int
    session: int
    opcode: int
    size: int
    offset: int
    data: bytes  # data[:size]

    @property
    def key(self) -> bytes:
        """What makes a request a re-send of another: all but the reply-only header fields."""
        head = struct.pack("<HBBBI", self.seq, self.session, self.opcode, self.size, self.offset)
        return head + self.data


def _parse(payload: bytes) -> _Request | None:
    """The request in a payload, None if too short to answer at all.

    MAVLink 2 trims trailing zeros off the wire, so a short payload is zero-padded, not refused.
    """
    if len(payload) < HEADER.size:
        return None
    body = payload[:PAYLOAD_LEN].ljust(PAYLOAD_LEN, b"\0")
    seq, session, opcode, size, _req, _burst, _pad, offset = HEADER.unpack_from(body)
    return _Request(seq, session, opcode, size, offset, body[HEADER.size:HEADER.size + size])


def _reply(req: _Request, opcode: int, data: bytes = b"", *, offset: int | None = None,
           seq_step: int = 1, burst_complete: bool = False) -> bytes:
    """A full reply payload: request seq + `seq_step`, the request's session and offset."""
    head = HEADER.pack((req.seq + seq_step) & 0xFFFF, req.session, opcode, len(data), req.opcode,
                       int(burst_complete), 0, req.offset if offset is None else offset)
    return (head + data).ljust(PAYLOAD_LEN, b"\0")


def _nak(req: _Request, code: int, errno_: int = 0) -> bytes:
    """NAK: data[0] the error, data[1] the errno only with FAILERRNO (size 1 or 2)."""
    data = bytes([code, errno_]) if code == ERR_FAILERRNO else bytes([code])
    return _reply(req, OP_NAK, data, burst_complete=req.opcode == OP_BURST_READ_FILE)


def _parts(raw: bytes) -> list[str]:
    """The components of a request path, which ends at its first NUL (MAVSDK counts the NUL in
    `size`, MAVProxy does not). "/x", "x" and "./x" are the same file under the root.

    ".." is refused outright rather than resolved: a path that climbs is never needed to name a
    file under the root, and refusing it keeps the check independent of what exists on disk.
    """
    text = os.fsdecode(raw.split(b"\0", 1)[0])
    parts = [part for part in text.split("/") if part not in ("", ".")]
    if ".." in parts:
        raise _Nak(ERR_FILENOTFOUND)
    return parts


def _key(parts: list[str]) -> str:
    return "/" + "/".join(parts)


def _chunk_len(size: int) -> int:
    """Bytes to read for a ReadFile/BurstReadFile `size`: 0 means as many as fit (ArduPilot)."""
    return size if 0 < size <= DATA_LEN else DATA_LEN


def _open_regular(path: Path, flags: int) -> int:
    """A descriptor on a regular file. O_NONBLOCK keeps a FIFO or device from stalling the caller;
    anything but a regular file is then refused (a directory with EISDIR)."""
    fd = os.open(path, flags | os.O_NONBLOCK, 0o644)
    try:
        mode = os.fstat(fd).st_mode
        if stat.S_ISDIR(mode):
            raise _Nak(ERR_FAILERRNO, errno.EISDIR)
        if not stat.S_ISREG(mode):
            raise _Nak(ERR_FAILERRNO, errno.EINVAL)
    except BaseException:
        os.close(fd)
        raise
    return fd


def _dir_entry(root: Path, directory: Path, name: str, with_time: bool) -> bytes:
    """"F<name>\\t<size>\\0" or "D<name>\\0" (with "\\t<mtime s>" appended, and "\\t0" as a
    directory's size, in the timed listing). An entry that cannot be shown (a tab in its name,
    too long for a payload, not a file or directory, leading out of the root, gone) is "S":
    skipped, but still counted, so the clients' offsets keep matching the server's indexes."""
    raw = os.fsencode(name)
    path = directory / name
    try:
        if b"\t" in raw or not path.resolve().is_relative_to(root):
            return b"S\0"
        info = os.stat(path)
    except (OSError, RuntimeError):
        return b"S\0"
    mtime = b"\t%d" % max(0, int(info.st_mtime)) if with_time else b""
    if stat.S_ISDIR(info.st_mode):
        entry = b"D" + raw + (b"\t0" + mtime if with_time else b"") + b"\0"
    elif stat.S_ISREG(info.st_mode):
        entry = b"F" + raw + b"\t%d" % info.st_size + mtime + b"\0"
    else:
        return b"S\0"
    return entry if len(entry) <= DATA_LEN else b"S\0"


@dataclass
class _Session:
    """An open file: a descriptor on a real file, or the bytes a virtual file gave when opened."""

    writable: bool
    path: Path | None  # None for a virtual file
    fd: int | None
    content: bytes
    size: int  # as announced when opened: reads stop there
    last_used_s: float

    def read(self, offset: int, length: int) -> bytes:
        length = min(length, self.size - offset)
        if length <= 0:
            return b""
        if self.fd is None:
            return self.content[offset:offset + length]
        return os.pread(self.fd, length, offset)

    def close(self) -> None:
        fd, self.fd, self.content = self.fd, None, b""
        if fd is not None:
            os.close(fd)


@dataclass(frozen=True)
class _Answered:
    key: bytes
    at_s: float
    replies: tuple[bytes, ...]


_Op = Callable[[_Request, bool], Iterator[bytes | None]]


class FtpServer:
    """A MAVLink FTP server confined to `root`.

    `virtual` maps absolute paths ("/@meta/general.json") to byte providers: readable like files
    (open, read, burst, CRC), never listed, never writable. Writes need `may_write=True` in the
    call and never touch `protected()` (the flight being recorded), anything under it, or a
    directory above it (renaming that would move the flight). Sessions idle longer than
    `session_timeout_s` by `clock_s` are closed; at most `max_sessions` are open at once.
    """

    def __init__(self, root: Path, *, virtual: Mapping[str, Callable[[], bytes]] | None = None,
                 protected: Callable[[], Path | None] = lambda: None,
                 clock_s: Callable[[], float] = time.monotonic,
                 max_sessions: int = 4, session_timeout_s: float = 10.0) -> None:
        self._root = Path(root)
        self._virtual = {_key([p for p in name.split("/") if p not in ("", ".")]): provider
                         for name, provider in (virtual or {}).items()}
        self._protected = protected
        self._clock_s = clock_s
        self._max_sessions = max_sessions
        self._session_timeout_s = session_timeout_s
        self._sessions: dict[int, _Session] = {}
        self._answered: dict[int, deque[_Answered]] = {}
        self._ops: dict[int, _Op] = {
            OP_NONE: self._op_none, OP_TERMINATE_SESSION: self._op_terminate,
            OP_RESET_SESSIONS: self._op_reset, OP_LIST_DIRECTORY: self._op_list,
            OP_LIST_DIRECTORY_WITH_TIME: self._op_list_with_time,
            OP_OPEN_FILE_RO: self._op_open_ro, OP_READ_FILE: self._op_read,
            OP_BURST_READ_FILE: self._op_burst, OP_CALC_FILE_CRC32: self._op_crc,
            OP_CREATE_FILE: self._op_create, OP_OPEN_FILE_WO: self._op_open_wo,
            OP_WRITE_FILE: self._op_write, OP_REMOVE_FILE: self._op_remove_file,
            OP_CREATE_DIRECTORY: self._op_mkdir, OP_REMOVE_DIRECTORY: self._op_rmdir,
            OP_RENAME: self._op_rename, OP_TRUNCATE_FILE: self._op_truncate,
        }

    def handle(self, payload: bytes, *, may_write: bool) -> Iterator[bytes | None]:
        """The replies to one request payload: complete 251-byte payloads, or None for "worked,
        no reply yet". Never raises; an ACK/NAK or a payload too short for a header gets none.
        Any bytes-like payload works, pymavlink's list of ints included."""
        try:
            request = _parse(bytes(payload))
        except (TypeError, ValueError):
            log.debug("FTP payload of type %s ignored", type(payload).__name__)
            request = None
        if request is None or request.opcode in (OP_ACK, OP_NAK):
            return iter(())
        return self._answer(request, may_write)

    def close(self) -> None:
        """Closes every session (the files they hold open)."""
        for sid in list(self._sessions):
            self._close(sid)

    # -- request plumbing ------------------------------------------------------------------------

    def _answer(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        """Upkeep, then either the remembered replies of a re-sent request or a fresh run."""
        try:
            now_s = self._clock_s()
            self._expire(now_s)
        except Exception:
            log.exception("FTP session upkeep failed")
            yield _nak(req, ERR_FAIL)
            return
        for done in self._answered.get(req.session, ()):
            if done.key == req.key:  # a re-send: its reply was lost, the work is done
                log.debug("FTP seq %d re-sent: earlier answer repeated", req.seq)
                yield from done.replies
                return
        replies: list[bytes] = []
        for reply in self._execute(req, may_write):
            if reply is not None:
                replies.append(reply)
            yield reply
        # Bursts are read again rather than kept; NOSESSIONSAVAILABLE did nothing and passes
        # (MAVSDK re-sends the same open after it, as ArduPilot's server also expects).
        last = replies[-1] if replies else b""
        busy = last[3:4] == bytes([OP_NAK]) and last[12:13] == bytes([ERR_NOSESSIONSAVAILABLE])
        if req.opcode != OP_BURST_READ_FILE and not busy:
            history = self._answered.setdefault(req.session, deque(maxlen=_REPLAY_DEPTH))
            history.append(_Answered(req.key, now_s, tuple(replies)))

    def _execute(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        """Runs one request. Every failure becomes a NAK; a failure the protocol has no word for
        is logged and answered with FAIL, so nothing escapes to the caller."""
        try:
            if req.size > DATA_LEN:
                raise _Nak(ERR_INVALIDDATASIZE)
            op = self._ops.get(req.opcode)
            if op is None:
                raise _Nak(ERR_UNKNOWNCOMMAND)
            yield from op(req, may_write)  # closing this generator closes op's as well
        except _Nak as nak:
            yield _nak(req, nak.code, nak.errno_)
        except OSError as exc:
            log.debug("FTP opcode %d: %s", req.opcode, exc)
            refusal = _nak_for(exc)
            yield _nak(req, refusal.code, refusal.errno_)
        except Exception:
            log.exception("FTP opcode %d failed", req.opcode)
            yield _nak(req, ERR_FAIL)

    def _expire(self, now_s: float) -> None:
        """Closes idle sessions (their ids are invalid from now on) and forgets old answers."""
        for sid, session in list(self._sessions.items()):
            if now_s - session.last_used_s > self._session_timeout_s:
                log.info("FTP session %d idle for %.1f s: closed", sid,
                         now_s - session.last_used_s)
                self._close(sid)
        for sid, history in list(self._answered.items()):
            while history and now_s - history[0].at_s > self._session_timeout_s:
                history.popleft()
            if not history:
                del self._answered[sid]

    # -- paths -----------------------------------------------------------------------------------

    def _locate(self, parts: list[str]) -> tuple[Path, Path]:
        """(entry, target) of a path under the root: the entry names a symlink itself, the target
        is what it resolves to. Both must lie under the root.

        Outside the root is answered FILENOTFOUND: the served tree is all that exists for a
        client, clients show it as "does not exist" (MAVSDK FileDoesNotExist, MAVProxy crccmp
        MISSING), and unlike FILEPROTECTED it does not reveal that something is there.
        """
        root = self._root.resolve()
        if not parts:
            return root, root
        try:
            parent = root.joinpath(*parts[:-1]).resolve()
            entry = parent / parts[-1]
            target = entry.resolve()
        except RuntimeError as exc:  # a symlink loop (Python 3.11)
            raise _Nak(ERR_FAILERRNO, errno.ELOOP) from exc
        if not (parent.is_relative_to(root) and target.is_relative_to(root)):
            raise _Nak(ERR_FILENOTFOUND)
        return entry, target

    def _writable(self, parts: list[str], may_write: bool) -> tuple[Path, Path]:
        """`_locate` for a change: FILEPROTECTED (the spec's "write protected", which MAVSDK shows
        as FileProtected) on a read-only call, a virtual file, the root or the recorded flight."""
        if not may_write or _key(parts) in self._virtual:
            raise _Nak(ERR_FILEPROTECTED)
        entry, target = self._locate(parts)
        if entry == self._root.resolve():
            raise _Nak(ERR_FILEPROTECTED)
        self._check_unprotected(entry, target)
        return entry, target

    def _check_unprotected(self, *paths: Path) -> None:
        flight = self._protected()
        if flight is None:
            return
        flight = Path(flight).resolve()
        for path in paths:
            if path.is_relative_to(flight) or flight.is_relative_to(path):
                raise _Nak(ERR_FILEPROTECTED)

    # -- sessions --------------------------------------------------------------------------------

    def _make_room(self, sid: int) -> None:
        """Before an open: the session the client chose reuses its slot, a new one needs a free
        slot. Reopening an open session replaces it (a retried open whose ACK was lost)."""
        if sid not in self._sessions and len(self._sessions) >= self._max_sessions:
            raise _Nak(ERR_NOSESSIONSAVAILABLE)

    def _install(self, sid: int, session: _Session) -> None:
        self._close(sid)
        self._sessions[sid] = session
        log.debug("FTP session %d open on %s", sid, session.path or "a virtual file")

    def _close(self, sid: int) -> None:
        session = self._sessions.pop(sid, None)
        if session is not None:
            session.close()

    def _session(self, sid: int, *, writable: bool) -> _Session:
        """An open session of the right kind: INVALIDSESSION when it is closed, timed out or was
        opened the other way (a read on a write session)."""
        session = self._sessions.get(sid)
        if session is None or session.writable != writable:
            raise _Nak(ERR_INVALIDSESSION)
        session.last_used_s = self._clock_s()
        return session

    def _file_session(self, path: Path, flags: int, *, writable: bool) -> _Session:
        fd = _open_regular(path, flags)
        try:
            size = os.fstat(fd).st_size
            if size > _MAX_FILE_BYTES:
                raise _Nak(ERR_FAILERRNO, errno.EFBIG)
        except BaseException:
            os.close(fd)
            raise
        return _Session(writable, path, fd, b"", size, self._clock_s())

    # -- operations: each yields its replies ------------------------------------------------------

    def _op_none(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        yield _reply(req, OP_ACK)

    def _op_terminate(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        # ACKed even when no such session is open: MAVSDK retries a lost ACK with a new seq and
        # would report a finished download as failed on a NAK here (ArduPilot also ACKs).
        self._close(req.session)
        yield _reply(req, OP_ACK)

    def _op_reset(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        self.close()
        yield _reply(req, OP_ACK)

    def _op_list(self, req: _Request, may_write: bool, *,
                 with_time: bool = False) -> Iterator[bytes | None]:
        """Entries from index `offset` of the sorted listing (stable across requests), packed
        while they fit; NAK EOF from the end on. Virtual files are not listed."""
        _entry, directory = self._locate(_parts(req.data))
        root = self._root.resolve()
        names = sorted(os.listdir(directory))
        if req.offset >= len(names):
            raise _Nak(ERR_EOF)
        if len(names) > _LIST_PIECE_ENTRIES:
            yield None
        packed = bytearray()
        for count, name in enumerate(itertools.islice(names, req.offset, None), 1):
            entry = _dir_entry(root, directory, name, with_time)
            if len(packed) + len(entry) > DATA_LEN:
                break
            packed += entry
            if count % _LIST_PIECE_ENTRIES == 0:
                yield None
        yield _reply(req, OP_ACK, bytes(packed))

    def _op_list_with_time(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        return self._op_list(req, may_write, with_time=True)

    def _op_open_ro(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        parts = _parts(req.data)
        self._make_room(req.session)
        provider = self._virtual.get(_key(parts))
        if provider is not None:
            content = bytes(provider())
            if len(content) > _MAX_FILE_BYTES:
                raise _Nak(ERR_FAILERRNO, errno.EFBIG)
            session = _Session(False, None, None, content, len(content), self._clock_s())
        else:
            _entry, target = self._locate(parts)
            session = self._file_session(target, os.O_RDONLY, writable=False)
        self._install(req.session, session)
        yield _reply(req, OP_ACK, _U32.pack(session.size))  # the file size, as the spec says

    def _op_read(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        session = self._session(req.session, writable=False)
        data = session.read(req.offset, _chunk_len(req.size))
        if not data:
            raise _Nak(ERR_EOF)
        yield _reply(req, OP_ACK, data)

    def _op_burst(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        """Data ACKs from `offset` to the end, `burst_complete` on the last. The session keeps
        the descriptor; the burst stops quietly if the session is closed or replaced meanwhile."""
        session = self._session(req.session, writable=False)
        chunk, offset = _chunk_len(req.size), req.offset
        if offset >= session.size:
            raise _Nak(ERR_EOF)
        for step in itertools.count(1):
            if self._sessions.get(req.session) is not session:
                return
            data = session.read(offset, chunk)
            if not data:  # the file shrank since it was opened
                raise _Nak(ERR_EOF)
            session.last_used_s = self._clock_s()
            last = offset + len(data) >= session.size or len(data) < chunk
            yield _reply(req, OP_ACK, data, offset=offset, seq_step=step, burst_complete=last)
            if last:
                return
            offset += len(data)

    def _op_crc(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        """MAVLink CRC32 of a file, 64 KiB between yields. The file is reopened for each piece, so
        no descriptor is held while the caller waits."""
        parts = _parts(req.data)
        provider = self._virtual.get(_key(parts))
        if provider is not None:
            yield _reply(req, OP_ACK, _U32.pack(mavlink_crc32(bytes(provider()))))
            return
        _entry, target = self._locate(parts)
        crc, offset = 0, 0
        while True:
            fd = _open_regular(target, os.O_RDONLY)
            try:
                piece = os.pread(fd, _CRC_PIECE_BYTES, offset)
            finally:
                os.close(fd)
            if not piece:
                break
            crc, offset = mavlink_crc32(piece, crc), offset + len(piece)
            yield None
        yield _reply(req, OP_ACK, _U32.pack(crc))

    def _op_create(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        # An existing file is truncated (O_CREAT|O_TRUNC as the spec's table says, and what
        # ArduPilot and MAVSDK's server do): re-uploading a file must work.
        return self._open_for_write(req, may_write, os.O_TRUNC)

    def _op_open_wo(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        return self._open_for_write(req, may_write, 0)

    def _open_for_write(self, req: _Request, may_write: bool,
                        extra_flags: int) -> Iterator[bytes | None]:
        _entry, target = self._writable(_parts(req.data), may_write)
        self._make_room(req.session)
        flags = os.O_WRONLY | os.O_CREAT | extra_flags
        session = self._file_session(target, flags, writable=True)
        self._install(req.session, session)
        # CreateFile ACKs without data as the spec says; OpenFileWO adds the size it found (as
        # MAVSDK's server does), which lets a client resume an upload.
        yield _reply(req, OP_ACK, b"" if extra_flags else _U32.pack(session.size))

    def _op_write(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        if not may_write:
            raise _Nak(ERR_FILEPROTECTED)
        session = self._session(req.session, writable=True)
        if session.fd is None or session.path is None:
            raise _Nak(ERR_INVALIDSESSION)
        self._check_unprotected(session.path)  # a flight may have started there since the open
        if os.pwrite(session.fd, req.data, req.offset) != len(req.data):
            raise _Nak(ERR_FAILERRNO, errno.ENOSPC)
        yield _reply(req, OP_ACK)  # the offset is echoed: MAVProxy finds the block by it

    def _op_remove_file(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        entry, _target = self._writable(_parts(req.data), may_write)
        os.unlink(entry)  # the entry: removing a symlink removes the link
        yield _reply(req, OP_ACK)

    def _op_mkdir(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        entry, _target = self._writable(_parts(req.data), may_write)
        os.mkdir(entry)
        yield _reply(req, OP_ACK)

    def _op_rmdir(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        entry, _target = self._writable(_parts(req.data), may_write)
        os.rmdir(entry)  # only an empty directory, as the spec says
        yield _reply(req, OP_ACK)

    def _op_rename(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        """"<from>\\0<to>" (MAVSDK adds a second NUL). An existing destination is refused with
        FILEEXISTS rather than replaced: a rename must not silently destroy a recorded flight."""
        names = req.data.split(b"\0")
        if len(names) < 2 or not names[0] or not names[1]:
            raise _Nak(ERR_INVALIDDATASIZE)
        source, _ = self._writable(_parts(names[0]), may_write)
        dest, _ = self._writable(_parts(names[1]), may_write)
        if os.path.lexists(dest):
            raise _Nak(ERR_FILEEXISTS)
        os.rename(source, dest)
        yield _reply(req, OP_ACK)

    def _op_truncate(self, req: _Request, may_write: bool) -> Iterator[bytes | None]:
        """Cuts a file to `offset` bytes; a longer `offset` is EINVAL, truncating never grows."""
        _entry, target = self._writable(_parts(req.data), may_write)
        fd = _open_regular(target, os.O_WRONLY)
        try:
            if req.offset > os.fstat(fd).st_size:
                raise _Nak(ERR_FAILERRNO, errno.EINVAL)
            os.ftruncate(fd, req.offset)
        finally:
            os.close(fd)
        yield _reply(req, OP_ACK)
