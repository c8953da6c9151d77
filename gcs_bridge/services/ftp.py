"""MAVLink FTP server over one directory tree: request payloads in, reply payloads out.

The wire format (header, opcodes, error codes, payload builders) is `ftp_wire`; this module
owns the sessions and the memory of answers; `ftp_tree` confines paths to the served root.

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
  MAVSDK and MAVProxy's `crclocal` compute; it is not zlib.crc32 (see `ftp_wire.mavlink_crc32`).
Sessions and remembered answers are keyed by the session byte alone, not by link: give each
client link its own FtpServer. Idle sessions are closed when the next request arrives (`close`
closes all). Not thread-safe: one thread calls `handle` and steps the iterators.
"""

from __future__ import annotations

import errno
import itertools
import logging
import os
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

from gcs_bridge.services.ftp_tree import ServedTree, open_regular
from gcs_bridge.services.ftp_wire import (
    DATA_LEN,
    ERR_EOF,
    ERR_FAIL,
    ERR_FAILERRNO,
    ERR_FILEEXISTS,
    ERR_FILEPROTECTED,
    ERR_INVALIDDATASIZE,
    ERR_INVALIDSESSION,
    ERR_NOSESSIONSAVAILABLE,
    ERR_UNKNOWNCOMMAND,
    MAX_FILE_BYTES,
    OP_ACK,
    OP_BURST_READ_FILE,
    OP_CALC_FILE_CRC32,
    OP_CREATE_DIRECTORY,
    OP_CREATE_FILE,
    OP_LIST_DIRECTORY,
    OP_LIST_DIRECTORY_WITH_TIME,
    OP_NAK,
    OP_NONE,
    OP_OPEN_FILE_RO,
    OP_OPEN_FILE_WO,
    OP_READ_FILE,
    OP_REMOVE_DIRECTORY,
    OP_REMOVE_FILE,
    OP_RENAME,
    OP_RESET_SESSIONS,
    OP_TERMINATE_SESSION,
    OP_TRUNCATE_FILE,
    OP_WRITE_FILE,
    U32,
    Nak,
    Request,
    chunk_len,
    dir_entry,
    mavlink_crc32,
    nak_for,
    nak_payload,
    parse_request,
    path_key,
    path_parts,
    reply_payload,
)

log = logging.getLogger(__name__)

_CRC_PIECE_BYTES = 64 * 1024  # CRC work between two yields
_LIST_PIECE_ENTRIES = 64  # directory entries looked at between two yields
_REPLAY_DEPTH = 16  # answers remembered per session for re-sent requests


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


_Op = Callable[[Request, bool], Iterator[bytes | None]]


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
        self._tree = ServedTree(root, virtual, protected)
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
            request = parse_request(bytes(payload))
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

    def _answer(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        """Upkeep, then either the remembered replies of a re-sent request or a fresh run."""
        try:
            now_s = self._clock_s()
            self._expire(now_s)
        except Exception:
            log.exception("FTP session upkeep failed")
            yield nak_payload(req, ERR_FAIL)
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

    def _execute(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        """Runs one request. Every failure becomes a NAK; a failure the protocol has no word for
        is logged and answered with FAIL, so nothing escapes to the caller."""
        try:
            if req.size > DATA_LEN:
                raise Nak(ERR_INVALIDDATASIZE)
            op = self._ops.get(req.opcode)
            if op is None:
                raise Nak(ERR_UNKNOWNCOMMAND)
            yield from op(req, may_write)  # closing this generator closes op's as well
        except Nak as nak:
            yield nak_payload(req, nak.code, nak.errno_)
        except OSError as exc:
            log.debug("FTP opcode %d: %s", req.opcode, exc)
            refusal = nak_for(exc)
            yield nak_payload(req, refusal.code, refusal.errno_)
        except Exception:
            log.exception("FTP opcode %d failed", req.opcode)
            yield nak_payload(req, ERR_FAIL)

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

    # -- sessions --------------------------------------------------------------------------------

    def _make_room(self, sid: int) -> None:
        """Before an open: the session the client chose reuses its slot, a new one needs a free
        slot. Reopening an open session replaces it (a retried open whose ACK was lost)."""
        if sid not in self._sessions and len(self._sessions) >= self._max_sessions:
            raise Nak(ERR_NOSESSIONSAVAILABLE)

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
            raise Nak(ERR_INVALIDSESSION)
        session.last_used_s = self._clock_s()
        return session

    def _file_session(self, path: Path, flags: int, *, writable: bool) -> _Session:
        fd = open_regular(path, flags)
        try:
            size = os.fstat(fd).st_size
            if size > MAX_FILE_BYTES:
                raise Nak(ERR_FAILERRNO, errno.EFBIG)
        except BaseException:
            os.close(fd)
            raise
        return _Session(writable, path, fd, b"", size, self._clock_s())

    # -- operations: each yields its replies ------------------------------------------------------

    def _op_none(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        yield reply_payload(req, OP_ACK)

    def _op_terminate(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        # ACKed even when no such session is open: MAVSDK retries a lost ACK with a new seq and
        # would report a finished download as failed on a NAK here (ArduPilot also ACKs).
        self._close(req.session)
        yield reply_payload(req, OP_ACK)

    def _op_reset(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        self.close()
        yield reply_payload(req, OP_ACK)

    def _op_list(self, req: Request, may_write: bool, *,
                 with_time: bool = False) -> Iterator[bytes | None]:
        """Entries from index `offset` of the sorted listing (stable across requests), packed
        while they fit; NAK EOF from the end on. Virtual files are not listed."""
        _entry, directory = self._tree.locate(path_parts(req.data))
        root = self._tree.root.resolve()
        names = sorted(os.listdir(directory))
        if req.offset >= len(names):
            raise Nak(ERR_EOF)
        if len(names) > _LIST_PIECE_ENTRIES:
            yield None
        packed = bytearray()
        for count, name in enumerate(itertools.islice(names, req.offset, None), 1):
            entry = dir_entry(root, directory, name, with_time)
            if len(packed) + len(entry) > DATA_LEN:
                break
            packed += entry
            if count % _LIST_PIECE_ENTRIES == 0:
                yield None
        yield reply_payload(req, OP_ACK, bytes(packed))

    def _op_list_with_time(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        return self._op_list(req, may_write, with_time=True)

    def _op_open_ro(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        parts = path_parts(req.data)
        self._make_room(req.session)
        provider = self._tree.virtual.get(path_key(parts))
        if provider is not None:
            content = bytes(provider())
            if len(content) > MAX_FILE_BYTES:
                raise Nak(ERR_FAILERRNO, errno.EFBIG)
            session = _Session(False, None, None, content, len(content), self._clock_s())
        else:
            _entry, target = self._tree.locate(parts)
            session = self._file_session(target, os.O_RDONLY, writable=False)
        self._install(req.session, session)
        yield reply_payload(req, OP_ACK, U32.pack(session.size))  # the file size, as the spec says

    def _op_read(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        session = self._session(req.session, writable=False)
        data = session.read(req.offset, chunk_len(req.size))
        if not data:
            raise Nak(ERR_EOF)
        yield reply_payload(req, OP_ACK, data)

    def _op_burst(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        """Data ACKs from `offset` to the end, `burst_complete` on the last. The session keeps
        the descriptor; the burst stops quietly if the session is closed or replaced meanwhile."""
        session = self._session(req.session, writable=False)
        chunk, offset = chunk_len(req.size), req.offset
        if offset >= session.size:
            raise Nak(ERR_EOF)
        for step in itertools.count(1):
            if self._sessions.get(req.session) is not session:
                return
            data = session.read(offset, chunk)
            if not data:  # the file shrank since it was opened
                raise Nak(ERR_EOF)
            session.last_used_s = self._clock_s()
            last = offset + len(data) >= session.size or len(data) < chunk
            yield reply_payload(req, OP_ACK, data, offset=offset, seq_step=step,
                                burst_complete=last)
            if last:
                return
            offset += len(data)

    def _op_crc(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        """MAVLink CRC32 of a file, 64 KiB between yields. The file is reopened for each piece, so
        no descriptor is held while the caller waits."""
        parts = path_parts(req.data)
        provider = self._tree.virtual.get(path_key(parts))
        if provider is not None:
            yield reply_payload(req, OP_ACK, U32.pack(mavlink_crc32(bytes(provider()))))
            return
        _entry, target = self._tree.locate(parts)
        crc, offset = 0, 0
        while True:
            fd = open_regular(target, os.O_RDONLY)
            try:
                piece = os.pread(fd, _CRC_PIECE_BYTES, offset)
            finally:
                os.close(fd)
            if not piece:
                break
            crc, offset = mavlink_crc32(piece, crc), offset + len(piece)
            yield None
        yield reply_payload(req, OP_ACK, U32.pack(crc))

    def _op_create(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        # An existing file is truncated (O_CREAT|O_TRUNC as the spec's table says, and what
        # ArduPilot and MAVSDK's server do): re-uploading a file must work.
        return self._open_for_write(req, may_write, os.O_TRUNC)

    def _op_open_wo(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        return self._open_for_write(req, may_write, 0)

    def _open_for_write(self, req: Request, may_write: bool,
                        extra_flags: int) -> Iterator[bytes | None]:
        _entry, target = self._tree.writable(path_parts(req.data), may_write)
        self._make_room(req.session)
        flags = os.O_WRONLY | os.O_CREAT | extra_flags
        session = self._file_session(target, flags, writable=True)
        self._install(req.session, session)
        # CreateFile ACKs without data as the spec says; OpenFileWO adds the size it found (as
        # MAVSDK's server does), which lets a client resume an upload.
        yield reply_payload(req, OP_ACK, b"" if extra_flags else U32.pack(session.size))

    def _op_write(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        if not may_write:
            raise Nak(ERR_FILEPROTECTED)
        session = self._session(req.session, writable=True)
        if session.fd is None or session.path is None:
            raise Nak(ERR_INVALIDSESSION)
        self._tree.check_unprotected(session.path)  # a flight may have started there since the open
        if os.pwrite(session.fd, req.data, req.offset) != len(req.data):
            raise Nak(ERR_FAILERRNO, errno.ENOSPC)
        yield reply_payload(req, OP_ACK)  # the offset is echoed: MAVProxy finds the block by it

    def _op_remove_file(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        entry, _target = self._tree.writable(path_parts(req.data), may_write)
        os.unlink(entry)  # the entry: removing a symlink removes the link
        yield reply_payload(req, OP_ACK)

    def _op_mkdir(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        entry, _target = self._tree.writable(path_parts(req.data), may_write)
        os.mkdir(entry)
        yield reply_payload(req, OP_ACK)

    def _op_rmdir(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        entry, _target = self._tree.writable(path_parts(req.data), may_write)
        os.rmdir(entry)  # only an empty directory, as the spec says
        yield reply_payload(req, OP_ACK)

    def _op_rename(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        """"<from>\\0<to>" (MAVSDK adds a second NUL). An existing destination is refused with
        FILEEXISTS rather than replaced: a rename must not silently destroy a recorded flight."""
        names = req.data.split(b"\0")
        if len(names) < 2 or not names[0] or not names[1]:
            raise Nak(ERR_INVALIDDATASIZE)
        source, _ = self._tree.writable(path_parts(names[0]), may_write)
        dest, _ = self._tree.writable(path_parts(names[1]), may_write)
        if os.path.lexists(dest):
            raise Nak(ERR_FILEEXISTS)
        os.rename(source, dest)
        yield reply_payload(req, OP_ACK)

    def _op_truncate(self, req: Request, may_write: bool) -> Iterator[bytes | None]:
        """Cuts a file to `offset` bytes; a longer `offset` is EINVAL, truncating never grows."""
        _entry, target = self._tree.writable(path_parts(req.data), may_write)
        fd = open_regular(target, os.O_WRONLY)
        try:
            if req.offset > os.fstat(fd).st_size:
                raise Nak(ERR_FAILERRNO, errno.EINVAL)
            os.ftruncate(fd, req.offset)
        finally:
            os.close(fd)
        yield reply_payload(req, OP_ACK)
