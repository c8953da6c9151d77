"""MAVLink FTP server (gcs_bridge.services.ftp.FtpServer): real files under tmp_path, no sockets, no sleeps.

The requests are shaped the way MAVSDK and MAVProxy send them (paths with and without the NUL in
`size`, client-chosen sessions, bursts of 239 or fewer bytes), and the replies are checked for
what those clients read from them.
"""

from __future__ import annotations

import os
import random
import struct
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from gcs_bridge.dialect import mavlink
from gcs_bridge.services import ftp, ftp_wire

U32 = struct.Struct("<I")


class Clock:
    """An injected clock_s: tests move time by hand."""

    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s


class Reply:
    def __init__(self, payload: bytes | None) -> None:
        assert payload is not None and len(payload) == ftp_wire.PAYLOAD_LEN
        (self.seq, self.session, self.opcode, self.size, self.req_opcode, self.burst_complete,
         _pad, self.offset) = ftp_wire.HEADER.unpack_from(payload)
        self.data = payload[ftp_wire.HEADER.size:ftp_wire.HEADER.size + self.size]
        assert payload[ftp_wire.HEADER.size + self.size:] == bytes(ftp_wire.DATA_LEN - self.size)

    @property
    def ack(self) -> bool:
        return self.opcode == ftp_wire.OP_ACK

    @property
    def error(self) -> int:
        assert self.opcode == ftp_wire.OP_NAK and self.size in (1, 2), vars(self)
        return self.data[0]


def request(opcode: int, data: bytes = b"", *, seq: int = 0, session: int = 0, offset: int = 0,
            size: int | None = None) -> bytes:
    size = len(data) if size is None else size
    return (ftp_wire.HEADER.pack(seq, session, opcode, size, 0, 0, 0, offset) + data).ljust(251, b"\0")


class Client:
    """Sends requests with increasing seq numbers and collects the replies."""

    def __init__(self, server: ftp.FtpServer, *, may_write: bool = False) -> None:
        self.server = server
        self.may_write = may_write
        self.seq = 100

    def send(self, opcode: int, data: bytes = b"", **kw: int) -> list[Reply]:
        kw.setdefault("seq", self.seq)
        self.seq += 1
        raw = list(self.server.handle(request(opcode, data, **kw), may_write=self.may_write))
        return [Reply(r) for r in raw if r is not None]

    def one(self, opcode: int, data: bytes = b"", **kw: int) -> Reply:
        replies = self.send(opcode, data, **kw)
        assert len(replies) == 1
        return replies[0]

    def listing(self, path: str, *, opcode: int = ftp_wire.OP_LIST_DIRECTORY) -> list[bytes]:
        """All entries, paged by offset the way the clients do, until NAK EOF."""
        entries: list[bytes] = []
        while True:
            r = self.one(opcode, path.encode() + b"\0", offset=len(entries))
            if not r.ack:
                assert r.error == ftp_wire.ERR_EOF
                return entries
            assert r.data.endswith(b"\0") and b"\0\0" not in r.data
            entries += r.data[:-1].split(b"\0")

    def download(self, path: str, *, session: int = 0) -> bytes:
        opened = self.one(ftp_wire.OP_OPEN_FILE_RO, path.encode(), session=session)
        assert opened.ack and opened.session == session and opened.size == 4
        out = b""
        while True:
            r = self.one(ftp_wire.OP_READ_FILE, session=session, offset=len(out), size=239)
            if not r.ack:
                assert r.error == ftp_wire.ERR_EOF
                break
            assert r.offset == len(out)
            out += r.data
        assert len(out) == U32.unpack(opened.data)[0]
        assert self.one(ftp_wire.OP_TERMINATE_SESSION, session=session).ack
        return out


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def reference_crc(data: bytes) -> int:
    """Bit by bit, from the MAVLink CRC page: reflected 0x04C11DB7, start 0, no final xor."""
    crc = 0
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xEDB88320 if crc & 1 else crc >> 1
    return crc


@pytest.fixture
def tree(tmp_path: Path) -> Path:
    root = tmp_path / "root"
    (root / "logs" / "f1").mkdir(parents=True)
    (root / "empty").mkdir()
    (root / "a.txt").write_bytes(b"hello")
    (root / "logs" / "f1" / "imu.bin").write_bytes(bytes(range(256)) * 10)
    (tmp_path / "secret.txt").write_bytes(b"outside")
    return root


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def make_server(clock: Clock) -> Iterator[Callable[..., ftp.FtpServer]]:
    """FtpServer(root, clock_s=clock, ...), closed (its sessions' files) after the test."""
    made: list[ftp.FtpServer] = []

    def make(root: Path, **kw: Any) -> ftp.FtpServer:
        made.append(ftp.FtpServer(root, clock_s=clock, **kw))
        return made[-1]

    yield make
    for server in made:
        server.close()


@pytest.fixture
def server(tree: Path, make_server: Callable[..., ftp.FtpServer]) -> ftp.FtpServer:
    return make_server(tree, virtual={"/@meta/general.json": lambda: b'{"v": 1}'},
                       protected=lambda: tree / "logs" / "f1")


# -- listing ---------------------------------------------------------------------------------------

def test_list_root_subdir_and_eof(server: ftp.FtpServer) -> None:
    c = Client(server)
    assert c.listing("/") == [b"Fa.txt\t5", b"Dempty", b"Dlogs"]
    assert c.listing("") == c.listing("/") == c.listing(".")
    assert c.listing("/logs/f1") == [b"Fimu.bin\t2560"]
    assert c.listing("logs/f1/") == [b"Fimu.bin\t2560"]
    first = c.one(ftp_wire.OP_LIST_DIRECTORY, b"/", offset=1)
    assert first.data == b"Dempty\0Dlogs\0"
    assert c.one(ftp_wire.OP_LIST_DIRECTORY, b"/", offset=3).error == ftp_wire.ERR_EOF
    assert c.one(ftp_wire.OP_LIST_DIRECTORY, b"/empty").error == ftp_wire.ERR_EOF  # empty: EOF at once
    assert c.one(ftp_wire.OP_LIST_DIRECTORY, b"/nope").error == ftp_wire.ERR_FILENOTFOUND
    assert c.one(ftp_wire.OP_LIST_DIRECTORY, b"/@meta").error == ftp_wire.ERR_FILENOTFOUND  # not listed
    not_dir = c.one(ftp_wire.OP_LIST_DIRECTORY, b"/a.txt")
    assert (not_dir.error, not_dir.data[1]) == (ftp_wire.ERR_FAILERRNO, 20)  # ENOTDIR


def test_list_with_time_gives_mtimes(server: ftp.FtpServer, tree: Path) -> None:
    os.utime(tree / "a.txt", (1747459200, 1747459200))
    entries = Client(server).listing("/", opcode=ftp_wire.OP_LIST_DIRECTORY_WITH_TIME)
    assert entries[0] == b"Fa.txt\t5\t1747459200"
    name, size, mtime = entries[2].split(b"\t")
    assert (name, size) == (b"Dlogs", b"0") and int(mtime) > 0


def test_list_pages_keep_every_entry_once_and_skip_what_cannot_be_shown(
        tree: Path, make_server: Callable[..., ftp.FtpServer]) -> None:
    big = tree / "big"
    big.mkdir()
    names = [f"file_{i:03d}_" + "x" * 40 for i in range(30)]
    for name in names:
        (big / name).write_bytes(b"12")
    (big / "tab\there").write_bytes(b"")  # cannot be shown: a tab separates fields
    (big / "out").symlink_to(tree.parent / "secret.txt")  # leads out of the root
    os.mkfifo(big / "pipe")
    c = Client(make_server(tree))
    pages = []
    offset = 0
    while (r := c.one(ftp_wire.OP_LIST_DIRECTORY, b"/big", offset=offset)).ack:
        assert r.size <= ftp_wire.DATA_LEN
        page = r.data[:-1].split(b"\0")
        pages.append(page)
        offset += len(page)
    assert r.error == ftp_wire.ERR_EOF and len(pages) > 5
    entries = [e for page in pages for e in page]
    shown = sorted(e[1:].split(b"\t")[0].decode() for e in entries if e != b"S")
    assert shown == sorted(names)
    assert entries.count(b"S") == 3 and offset == len(os.listdir(big))


def test_a_huge_directory_yields_between_pieces(
        tree: Path, make_server: Callable[..., ftp.FtpServer]) -> None:
    many = tree / "many"
    many.mkdir()
    for i in range(300):
        (many / f"{i:04d}").write_bytes(b"")
    out = list(make_server(tree).handle(
        request(ftp_wire.OP_LIST_DIRECTORY, b"/many"), may_write=False))
    assert out[0] is None and out[-1] is not None and Reply(out[-1]).ack


# -- reading ---------------------------------------------------------------------------------------

def test_open_and_read_whole_file_byte_exact(server: ftp.FtpServer, tree: Path) -> None:
    c = Client(server)
    assert c.download("/logs/f1/imu.bin", session=7) == (tree / "logs/f1/imu.bin").read_bytes()
    assert c.download("a.txt") == b"hello"
    # MAVSDK counts the path's NUL in size; anything after it is ignored
    assert c.one(ftp_wire.OP_OPEN_FILE_RO, b"/a.txt\0junk").ack


def test_read_sizes_offsets_and_eof(server: ftp.FtpServer) -> None:
    c = Client(server)
    assert c.one(ftp_wire.OP_OPEN_FILE_RO, b"/logs/f1/imu.bin", session=3).ack
    r = c.one(ftp_wire.OP_READ_FILE, session=3, offset=250, size=10)
    assert (r.offset, r.data) == (250, bytes([250, 251, 252, 253, 254, 255, 0, 1, 2, 3]))
    assert c.one(ftp_wire.OP_READ_FILE, session=3, offset=2550, size=239).data == bytes(range(246, 256))
    assert c.one(ftp_wire.OP_READ_FILE, session=3, offset=0, size=0).size == 239  # 0: as much as fits
    assert c.one(ftp_wire.OP_READ_FILE, session=3, offset=2560, size=10).error == ftp_wire.ERR_EOF
    assert c.one(ftp_wire.OP_READ_FILE, session=3, offset=99999).error == ftp_wire.ERR_EOF
    assert c.one(ftp_wire.OP_READ_FILE, session=3, size=240).error == ftp_wire.ERR_INVALIDDATASIZE


def burst(c: Client, session: int, offset: int = 0, size: int = 239,
          seq: int = 500) -> list[Reply]:
    return c.send(ftp_wire.OP_BURST_READ_FILE, session=session, offset=offset, size=size, seq=seq)


@pytest.mark.parametrize("length", [1, 238, 239, 240, 478, 2560, 5000])
def test_burst_read_byte_exact(tree: Path, make_server: Callable[..., ftp.FtpServer],
                               length: int) -> None:
    content = random.Random(length).randbytes(length)
    (tree / "blob").write_bytes(content)
    c = Client(make_server(tree))
    opened = c.one(ftp_wire.OP_OPEN_FILE_RO, b"/blob\0", session=9)
    assert U32.unpack(opened.data)[0] == length
    packets = burst(c, 9)
    assert all(p.ack and p.session == 9 and p.req_opcode == ftp_wire.OP_BURST_READ_FILE
               for p in packets)
    assert b"".join(p.data for p in packets) == content
    assert [p.offset for p in packets] == list(range(0, length, 239))
    assert [p.seq for p in packets] == [501 + i for i in range(len(packets))]
    assert [p.burst_complete for p in packets] == [0] * (len(packets) - 1) + [1]
    # MAVProxy asks again after a full last packet: the end of the file is NAK EOF
    end = burst(c, 9, offset=length)
    assert len(end) == 1 and end[0].error == ftp_wire.ERR_EOF and end[0].burst_complete == 1


def test_burst_honours_the_requested_size_and_offset(server: ftp.FtpServer, tree: Path) -> None:
    c = Client(server)
    c.one(ftp_wire.OP_OPEN_FILE_RO, b"/logs/f1/imu.bin", session=1)
    packets = burst(c, 1, offset=1000, size=80)
    assert {p.size for p in packets[:-1]} == {80} and packets[-1].size == 1560 % 80
    assert b"".join(p.data for p in packets) == (tree / "logs/f1/imu.bin").read_bytes()[1000:]


def test_empty_file_burst_and_read_are_eof(
        tree: Path, make_server: Callable[..., ftp.FtpServer]) -> None:
    (tree / "nothing").write_bytes(b"")
    c = Client(make_server(tree))
    opened = c.one(ftp_wire.OP_OPEN_FILE_RO, b"nothing")
    assert opened.data == U32.pack(0)
    assert burst(c, 0)[0].error == ftp_wire.ERR_EOF
    assert c.one(ftp_wire.OP_READ_FILE).error == ftp_wire.ERR_EOF


def test_a_growing_file_is_served_as_announced(server: ftp.FtpServer, tree: Path) -> None:
    c = Client(server)
    opened = c.one(ftp_wire.OP_OPEN_FILE_RO, b"/a.txt")
    with open(tree / "a.txt", "ab") as f:
        f.write(b" world")
    assert opened.data == U32.pack(5)
    assert b"".join(p.data for p in burst(c, 0)) == b"hello"
    assert c.one(ftp_wire.OP_READ_FILE, offset=5).error == ftp_wire.ERR_EOF


def test_crc32_is_mavlinks_crc(tree: Path, make_server: Callable[..., ftp.FtpServer]) -> None:
    content = random.Random(1).randbytes(200_000)  # more than three 64 KiB pieces
    (tree / "big.bin").write_bytes(content)
    server = make_server(tree)
    baseline = open_fds()
    out = []
    for reply in server.handle(request(ftp_wire.OP_CALC_FILE_CRC32, b"/big.bin"), may_write=False):
        assert open_fds() == baseline  # nothing held open while the caller waits
        out.append(reply)
    assert out[:4] == [None] * 4 and out[-1] is not None
    crc = U32.unpack(Reply(out[-1]).data)[0]
    # what MAVSDK's Crc32 and MAVProxy's crclocal compute; plain zlib.crc32 differs
    assert crc == zlib.crc32(content, 0xFFFFFFFF) ^ 0xFFFFFFFF == ftp_wire.mavlink_crc32(content)
    assert crc != zlib.crc32(content)
    assert ftp_wire.mavlink_crc32(b"123456789") == reference_crc(b"123456789")
    assert ftp_wire.mavlink_crc32(content[:999]) == reference_crc(content[:999])
    c = Client(server)
    assert c.one(ftp_wire.OP_CALC_FILE_CRC32, b"/a.txt\0").data == U32.pack(reference_crc(b"hello"))
    assert c.one(ftp_wire.OP_CALC_FILE_CRC32, b"/nope").error == ftp_wire.ERR_FILENOTFOUND
    assert c.one(ftp_wire.OP_CALC_FILE_CRC32, b"/empty").data[1] == 21  # EISDIR


# -- virtual files ---------------------------------------------------------------------------------

def test_virtual_files_read_but_never_listed_or_written(server: ftp.FtpServer) -> None:
    c = Client(server)
    assert c.download("/@meta/general.json") == b'{"v": 1}'
    assert c.download("@meta/general.json") == b'{"v": 1}'  # ArduPilot-style, no leading "/"
    c.one(ftp_wire.OP_OPEN_FILE_RO, b"/@meta/general.json", session=2)
    assert b"".join(p.data for p in burst(c, 2)) == b'{"v": 1}'
    crc = c.one(ftp_wire.OP_CALC_FILE_CRC32, b"/@meta/general.json").data
    assert crc == U32.pack(reference_crc(b'{"v": 1}'))
    w = Client(server, may_write=True)
    for op in (ftp_wire.OP_CREATE_FILE, ftp_wire.OP_OPEN_FILE_WO, ftp_wire.OP_REMOVE_FILE, ftp_wire.OP_TRUNCATE_FILE):
        assert w.one(op, b"/@meta/general.json").error == ftp_wire.ERR_FILEPROTECTED
    assert w.one(ftp_wire.OP_RENAME, b"/@meta/general.json\0/x").error == ftp_wire.ERR_FILEPROTECTED


def test_a_failing_provider_is_a_nak_fail(tree: Path, make_server: Callable[..., ftp.FtpServer],
                                          caplog: pytest.LogCaptureFixture) -> None:
    def broken() -> bytes:
        raise RuntimeError("no metadata")

    c = Client(make_server(tree, virtual={"/@meta/x": broken}))
    assert c.one(ftp_wire.OP_OPEN_FILE_RO, b"/@meta/x").error == ftp_wire.ERR_FAIL
    assert c.one(ftp_wire.OP_CALC_FILE_CRC32, b"/@meta/x").error == ftp_wire.ERR_FAIL
    assert "no metadata" in caplog.text


# -- sessions --------------------------------------------------------------------------------------

def test_sessions_are_the_clients_and_limited(server: ftp.FtpServer) -> None:
    c = Client(server)
    for sid in (0, 17, 200, 255):
        assert c.one(ftp_wire.OP_OPEN_FILE_RO, b"/a.txt", session=sid).session == sid
    assert c.one(ftp_wire.OP_OPEN_FILE_RO, b"/a.txt", session=5).error == ftp_wire.ERR_NOSESSIONSAVAILABLE
    # a retried open on a session still open replaces it (MAVSDK retries with a new seq)
    assert c.one(ftp_wire.OP_OPEN_FILE_RO, b"/logs/f1/imu.bin", session=17).data == U32.pack(2560)
    assert c.one(ftp_wire.OP_READ_FILE, session=17, offset=255, size=1).data == b"\xff"
    assert c.one(ftp_wire.OP_TERMINATE_SESSION, session=17).ack
    assert c.one(ftp_wire.OP_READ_FILE, session=17).error == ftp_wire.ERR_INVALIDSESSION
    assert c.one(ftp_wire.OP_TERMINATE_SESSION, session=17).ack  # closing twice is still done
    assert c.one(ftp_wire.OP_OPEN_FILE_RO, b"/a.txt", session=5).ack
    assert c.one(ftp_wire.OP_RESET_SESSIONS).ack
    for sid in (0, 5, 200, 255):
        assert c.one(ftp_wire.OP_READ_FILE, session=sid).error == ftp_wire.ERR_INVALIDSESSION
        assert c.one(ftp_wire.OP_BURST_READ_FILE, session=sid).error == ftp_wire.ERR_INVALIDSESSION


def test_bad_session_and_session_timeout(server: ftp.FtpServer, clock: Clock) -> None:
    c = Client(server)
    assert c.one(ftp_wire.OP_READ_FILE, session=3).error == ftp_wire.ERR_INVALIDSESSION
    assert c.one(ftp_wire.OP_OPEN_FILE_RO, b"/a.txt", session=3).ack
    clock.now_s += 9.5
    assert c.one(ftp_wire.OP_READ_FILE, session=3).ack  # use keeps it alive
    clock.now_s += 9.5
    assert c.one(ftp_wire.OP_READ_FILE, session=3, offset=1).ack
    clock.now_s += 10.5
    assert c.one(ftp_wire.OP_READ_FILE, session=3).error == ftp_wire.ERR_INVALIDSESSION
    for sid in range(4):  # the timed-out session no longer takes a slot
        assert c.one(ftp_wire.OP_OPEN_FILE_RO, b"/a.txt", session=sid).ack


def test_read_and_write_sessions_do_not_mix(server: ftp.FtpServer) -> None:
    w = Client(server, may_write=True)
    assert w.one(ftp_wire.OP_OPEN_FILE_RO, b"/a.txt", session=1).ack
    assert w.one(ftp_wire.OP_WRITE_FILE, b"x", session=1).error == ftp_wire.ERR_INVALIDSESSION
    assert w.one(ftp_wire.OP_CREATE_FILE, b"/new", session=2).ack
    assert w.one(ftp_wire.OP_READ_FILE, session=2).error == ftp_wire.ERR_INVALIDSESSION


# -- confinement -----------------------------------------------------------------------------------

def test_paths_outside_the_root_are_not_found(server: ftp.FtpServer, tree: Path) -> None:
    (tree / "link_out").symlink_to(tree.parent / "secret.txt")
    (tree / "dir_out").symlink_to(tree.parent)
    (tree / "link_in").symlink_to(tree / "a.txt")
    c = Client(server)
    w = Client(server, may_write=True)
    for path in (b"/../secret.txt", b"../secret.txt", b"logs/../../secret.txt",
                 b"/link_out", b"/dir_out/secret.txt", b"/logs/../a.txt"):
        assert c.one(ftp_wire.OP_OPEN_FILE_RO, path).error == ftp_wire.ERR_FILENOTFOUND, path
        assert c.one(ftp_wire.OP_CALC_FILE_CRC32, path).error == ftp_wire.ERR_FILENOTFOUND, path
        assert w.one(ftp_wire.OP_CREATE_FILE, path).error == ftp_wire.ERR_FILENOTFOUND, path
        assert w.one(ftp_wire.OP_REMOVE_FILE, path).error == ftp_wire.ERR_FILENOTFOUND, path
    assert c.one(ftp_wire.OP_LIST_DIRECTORY, b"/dir_out").error == ftp_wire.ERR_FILENOTFOUND
    assert c.one(ftp_wire.OP_LIST_DIRECTORY, b"/..").error == ftp_wire.ERR_FILENOTFOUND
    assert w.one(ftp_wire.OP_RENAME, b"/a.txt\0/../moved").error == ftp_wire.ERR_FILENOTFOUND
    assert (tree.parent / "secret.txt").read_bytes() == b"outside"
    assert not (tree.parent / "moved").exists()
    assert c.download("/link_in") == b"hello"  # a link that stays inside is fine


# -- writing ---------------------------------------------------------------------------------------

WRITE_OPS = [(ftp_wire.OP_CREATE_FILE, b"/new.txt"), (ftp_wire.OP_OPEN_FILE_WO, b"/a.txt"),
             (ftp_wire.OP_REMOVE_FILE, b"/a.txt"), (ftp_wire.OP_CREATE_DIRECTORY, b"/d"),
             (ftp_wire.OP_REMOVE_DIRECTORY, b"/empty"), (ftp_wire.OP_RENAME, b"/a.txt\0/b.txt"),
             (ftp_wire.OP_TRUNCATE_FILE, b"/a.txt")]


@pytest.mark.parametrize(("opcode", "data"), WRITE_OPS)
def test_read_only_refuses_every_change(server: ftp.FtpServer, tree: Path, opcode: int,
                                        data: bytes) -> None:
    before = sorted(p.name for p in tree.rglob("*"))
    assert Client(server).one(opcode, data).error == ftp_wire.ERR_FILEPROTECTED
    assert sorted(p.name for p in tree.rglob("*")) == before
    assert (tree / "a.txt").read_bytes() == b"hello"


def test_write_needs_may_write_on_every_request(server: ftp.FtpServer, tree: Path) -> None:
    assert Client(server, may_write=True).one(ftp_wire.OP_CREATE_FILE, b"/n", session=4).ack
    assert Client(server).one(ftp_wire.OP_WRITE_FILE, b"abc", session=4).error == ftp_wire.ERR_FILEPROTECTED
    assert (tree / "n").read_bytes() == b""


@pytest.mark.parametrize(("opcode", "data"), [
    (ftp_wire.OP_CREATE_FILE, b"/logs/f1/new.bin"), (ftp_wire.OP_OPEN_FILE_WO, b"/logs/f1/imu.bin"),
    (ftp_wire.OP_REMOVE_FILE, b"/logs/f1/imu.bin"), (ftp_wire.OP_CREATE_DIRECTORY, b"/logs/f1/sub"),
    (ftp_wire.OP_REMOVE_DIRECTORY, b"/logs/f1"), (ftp_wire.OP_REMOVE_DIRECTORY, b"/logs"),
    (ftp_wire.OP_RENAME, b"/logs/f1/imu.bin\0/imu.bin"), (ftp_wire.OP_RENAME, b"/logs\0/old_logs"),
    (ftp_wire.OP_RENAME, b"/a.txt\0/logs/f1/a.txt"), (ftp_wire.OP_TRUNCATE_FILE, b"/logs/f1/imu.bin"),
    (ftp_wire.OP_REMOVE_DIRECTORY, b"/"), (ftp_wire.OP_RENAME, b"/\0/x"),
])
def test_the_recorded_flight_and_the_root_are_protected(server: ftp.FtpServer, tree: Path,
                                                        opcode: int, data: bytes) -> None:
    assert Client(server, may_write=True).one(opcode, data).error == ftp_wire.ERR_FILEPROTECTED
    assert (tree / "logs/f1/imu.bin").read_bytes() == bytes(range(256)) * 10
    assert sorted(p.name for p in (tree / "logs/f1").iterdir()) == ["imu.bin"]


def test_a_write_session_stops_when_its_flight_starts(
        tree: Path, make_server: Callable[..., ftp.FtpServer]) -> None:
    flight: list[Path | None] = [None]
    w = Client(make_server(tree, protected=lambda: flight[0]), may_write=True)
    assert w.one(ftp_wire.OP_CREATE_FILE, b"/logs/f1/notes", session=1).ack
    assert w.one(ftp_wire.OP_WRITE_FILE, b"ok", session=1).ack
    flight[0] = tree / "logs" / "f1"
    assert w.one(ftp_wire.OP_WRITE_FILE, b"no", session=1, offset=2).error == ftp_wire.ERR_FILEPROTECTED
    assert (tree / "logs/f1/notes").read_bytes() == b"ok"


def test_write_path_works(server: ftp.FtpServer, tree: Path) -> None:
    w = Client(server, may_write=True)
    content = random.Random(2).randbytes(1000)
    assert w.one(ftp_wire.OP_CREATE_DIRECTORY, b"/up\0").ack
    created = w.one(ftp_wire.OP_CREATE_FILE, b"/up/file.bin\0", session=6)
    assert created.ack and created.session == 6 and created.size == 0
    blocks = list(range(0, len(content), 239))
    for offset in reversed(blocks):  # out of order, as MAVProxy resends
        r = w.one(ftp_wire.OP_WRITE_FILE, content[offset:offset + 239], session=6, offset=offset)
        assert r.ack and r.offset == offset and r.size == 0
    assert w.one(ftp_wire.OP_TERMINATE_SESSION, session=6).ack
    assert (tree / "up/file.bin").read_bytes() == content
    assert w.one(ftp_wire.OP_CALC_FILE_CRC32, b"/up/file.bin").data == U32.pack(reference_crc(content))
    appended = w.one(ftp_wire.OP_OPEN_FILE_WO, b"/up/file.bin", session=6)
    assert appended.data == U32.pack(1000)
    assert w.one(ftp_wire.OP_WRITE_FILE, b"END", session=6, offset=1000).ack
    assert w.one(ftp_wire.OP_TRUNCATE_FILE, b"/up/file.bin", offset=10).ack
    assert (tree / "up/file.bin").read_bytes() == content[:10]
    truncate_more = w.one(ftp_wire.OP_TRUNCATE_FILE, b"/up/file.bin", offset=11)
    assert (truncate_more.error, truncate_more.data[1]) == (ftp_wire.ERR_FAILERRNO, 22)
    assert w.one(ftp_wire.OP_RENAME, b"/up/file.bin\0/up/moved.bin").ack  # MAVProxy: one NUL
    assert w.one(ftp_wire.OP_RENAME, b"/up/moved.bin\0/a.txt\0").error == ftp_wire.ERR_FILEEXISTS  # MAVSDK
    assert w.one(ftp_wire.OP_RENAME, b"/up/moved.bin").error == ftp_wire.ERR_INVALIDDATASIZE
    assert w.one(ftp_wire.OP_REMOVE_DIRECTORY, b"/up").data[:2] == bytes([ftp_wire.ERR_FAILERRNO, 39])
    assert w.one(ftp_wire.OP_REMOVE_FILE, b"/up/moved.bin").ack
    assert w.one(ftp_wire.OP_REMOVE_FILE, b"/up/moved.bin").error == ftp_wire.ERR_FILENOTFOUND
    assert w.one(ftp_wire.OP_REMOVE_DIRECTORY, b"/up").ack
    assert w.one(ftp_wire.OP_CREATE_DIRECTORY, b"/empty").error == ftp_wire.ERR_FILEEXISTS
    assert w.one(ftp_wire.OP_CREATE_FILE, b"/no/such/dir/x").error == ftp_wire.ERR_FILENOTFOUND
    assert w.one(ftp_wire.OP_CREATE_FILE, b"/empty").data[:2] == bytes([ftp_wire.ERR_FAILERRNO, 21])
    assert w.one(ftp_wire.OP_CREATE_FILE, b"/a.txt").ack  # an existing file is truncated
    assert (tree / "a.txt").read_bytes() == b""


def test_removing_a_symlink_removes_the_link(server: ftp.FtpServer, tree: Path) -> None:
    (tree / "alias").symlink_to(tree / "a.txt")
    assert Client(server, may_write=True).one(ftp_wire.OP_REMOVE_FILE, b"/alias").ack
    assert not (tree / "alias").is_symlink() and (tree / "a.txt").read_bytes() == b"hello"


# -- re-sent requests ------------------------------------------------------------------------------

def test_a_resent_request_gets_the_same_reply_and_is_not_done_twice(
        server: ftp.FtpServer, tree: Path) -> None:
    create = request(ftp_wire.OP_CREATE_FILE, b"/r.bin", seq=40, session=8)
    write = request(ftp_wire.OP_WRITE_FILE, b"payload", seq=41, session=8)
    first = list(server.handle(create, may_write=True))
    assert Reply(first[0]).ack
    assert Reply(next(server.handle(write, may_write=True))).ack
    # the CreateFile arrives again (a duplicate or a retry): repeated, not executed again
    assert list(server.handle(create, may_write=True)) == first
    assert (tree / "r.bin").read_bytes() == b"payload"
    remove = request(ftp_wire.OP_REMOVE_FILE, b"/r.bin", seq=42, session=8)
    removed = list(server.handle(remove, may_write=True))
    assert list(server.handle(remove, may_write=True)) == removed and Reply(removed[0]).ack
    mkdir = request(ftp_wire.OP_CREATE_DIRECTORY, b"/m", seq=43, session=8)
    assert list(server.handle(mkdir, may_write=True)) == list(server.handle(mkdir, may_write=True))
    # a new seq is a new request
    again = Reply(next(server.handle(request(ftp_wire.OP_CREATE_DIRECTORY, b"/m", seq=44, session=8),
                                     may_write=True)))
    assert again.error == ftp_wire.ERR_FILEEXISTS
    # the same seq on another session is another client's request
    other = Reply(next(server.handle(request(ftp_wire.OP_CREATE_DIRECTORY, b"/m", seq=43, session=9),
                                     may_write=True)))
    assert other.error == ftp_wire.ERR_FILEEXISTS


def test_no_sessions_available_is_not_remembered(server: ftp.FtpServer) -> None:
    c = Client(server)
    for sid in range(4):
        assert c.one(ftp_wire.OP_OPEN_FILE_RO, b"/a.txt", session=sid).ack
    open_again = request(ftp_wire.OP_OPEN_FILE_RO, b"/a.txt", seq=7, session=9)
    busy = Reply(next(server.handle(open_again, may_write=False)))
    assert busy.error == ftp_wire.ERR_NOSESSIONSAVAILABLE
    assert c.one(ftp_wire.OP_TERMINATE_SESSION, session=2).ack
    # MAVSDK sends the very same open again after a while: now there is room
    assert Reply(next(server.handle(open_again, may_write=False))).ack


def test_remembered_answers_expire(server: ftp.FtpServer, clock: Clock, tree: Path) -> None:
    mkdir = request(ftp_wire.OP_CREATE_DIRECTORY, b"/m", seq=1)
    assert Reply(next(server.handle(mkdir, may_write=True))).ack
    clock.now_s += 11
    assert Reply(next(server.handle(mkdir, may_write=True))).error == ftp_wire.ERR_FILEEXISTS


def test_reply_seq_wraps(server: ftp.FtpServer) -> None:
    assert Client(server).one(ftp_wire.OP_NONE, seq=0xFFFF).seq == 0
    c = Client(server)
    c.one(ftp_wire.OP_OPEN_FILE_RO, b"/logs/f1/imu.bin")
    assert [p.seq for p in burst(c, 0, seq=0xFFFE)[:3]] == [0xFFFF, 0, 1]


# -- robustness ------------------------------------------------------------------------------------

def test_replies_and_malformed_payloads_never_raise(server: ftp.FtpServer) -> None:
    assert list(server.handle(request(ftp_wire.OP_ACK), may_write=True)) == []
    assert list(server.handle(request(ftp_wire.OP_NAK), may_write=True)) == []
    assert list(server.handle(b"", may_write=True)) == []
    assert list(server.handle(b"\x01" * 11, may_write=True)) == []
    assert list(server.handle(None, may_write=True)) == []  # type: ignore[arg-type]
    c = Client(server)
    assert c.one(99).error == ftp_wire.ERR_UNKNOWNCOMMAND
    assert c.one(ftp_wire.OP_NONE).ack
    too_big = c.one(ftp_wire.OP_WRITE_FILE, b"x" * 239, size=240)
    assert too_big.error == ftp_wire.ERR_INVALIDDATASIZE and too_big.req_opcode == ftp_wire.OP_WRITE_FILE
    short = Reply(next(server.handle(request(ftp_wire.OP_OPEN_FILE_RO, b"/a.txt")[:18],
                                     may_write=False)))
    assert short.ack  # MAVLink 2 trims trailing zeros: a short payload is zero-padded
    rng = random.Random(3)
    for _ in range(3000):
        payload = rng.randbytes(rng.choice([0, 5, 12, 13, 40, 251, 300]))
        if len(payload) > 3 and rng.random() < 0.8:  # mostly known opcodes, to get past them
            payload = payload[:3] + bytes([rng.randrange(18)]) + payload[4:]
        for reply in server.handle(payload, may_write=rng.random() < 0.5):
            assert reply is None or len(reply) == ftp_wire.PAYLOAD_LEN
    assert Client(server).download("/a.txt", session=77) == b"hello"


def test_abandoned_iterators_leak_nothing(server: ftp.FtpServer, tree: Path) -> None:
    (tree / "long.bin").write_bytes(bytes(100_000))
    baseline = open_fds()
    c = Client(server)
    c.one(ftp_wire.OP_OPEN_FILE_RO, b"/long.bin", session=1)
    assert open_fds() == baseline + 1  # the session's descriptor
    replies = server.handle(request(ftp_wire.OP_BURST_READ_FILE, session=1, size=239), may_write=False)
    assert Reply(next(replies)).offset == 0 and Reply(next(replies)).offset == 239
    del replies  # abandoned: the caller just drops it
    crc = server.handle(request(ftp_wire.OP_CALC_FILE_CRC32, b"/long.bin"), may_write=False)
    assert next(crc) is None
    del crc
    assert open_fds() == baseline + 1
    # a burst still pending when its session closes stops quietly
    pending = server.handle(request(ftp_wire.OP_BURST_READ_FILE, session=1), may_write=False)
    assert Reply(next(pending)).ack
    assert c.one(ftp_wire.OP_TERMINATE_SESSION, session=1).ack
    assert list(pending) == []
    assert open_fds() == baseline
    c.one(ftp_wire.OP_OPEN_FILE_RO, b"/long.bin", session=2)
    c.one(ftp_wire.OP_OPEN_FILE_RO, b"/a.txt", session=3)
    server.close()
    assert open_fds() == baseline


def test_pymavlink_mavftp_client_round_trip(tree: Path, tmp_path: Path,
                                            make_server: Callable[..., ftp.FtpServer]) -> None:
    """pymavlink's own FTP client (list, burst get, put) against the server, in-process."""
    from pymavlink import mavftp

    server = make_server(tree, virtual={"/@meta/general.json": lambda: b'{"v": 1}'})

    class Master:  # the two calls mavftp makes on a connection
        source_system, source_component = 255, 190

        def __init__(self) -> None:
            self.mav = self
            self.inbox: list[mavlink.MAVLink_message] = []

        def file_transfer_protocol_send(self, _net: int, _sys: int, _comp: int,
                                        payload: bytes) -> None:
            for reply in server.handle(bytes(payload), may_write=True):
                if reply is not None:
                    self.inbox.append(mavlink.MAVLink_file_transfer_protocol_message(
                        0, 255, 190, list(reply)))

        def recv_match(self, **_kw: Any) -> mavlink.MAVLink_message | None:
            return self.inbox.pop(0) if self.inbox else None

    content = random.Random(6).randbytes(20_000)
    (tree / "logs" / "big.bin").write_bytes(content)
    client = mavftp.MAVFTP(Master(), 1, 1)
    assert client.cmd_list(["/"]).error_code == 0
    assert sorted((e.name, e.size_b) for e in client.list_result) == [
        ("a.txt", 5), ("empty", 0), ("logs", 0)]
    for remote, expected in (("/logs/big.bin", content), ("@meta/general.json", b'{"v": 1}')):
        local = tmp_path / "got.bin"
        assert client.cmd_get([remote, str(local)]).error_code == 0  # starts it; the CLI then waits
        assert client.process_ftp_reply("get", timeout=5).error_code == 0
        assert local.read_bytes() == expected
    (tmp_path / "up.bin").write_bytes(content[:3333])
    assert client.cmd_put([str(tmp_path / "up.bin"), "/up.bin"]).error_code == 0
    assert client.process_ftp_reply("put", timeout=5).error_code == 0
    assert (tree / "up.bin").read_bytes() == content[:3333]
    # (its crc command ends only after 3.7 s of silence, whatever the server does: left out)
