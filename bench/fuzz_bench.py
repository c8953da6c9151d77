"""Long fuzzing run of every parser that takes outside bytes, with line and branch coverage.

Run: `python bench/fuzz_bench.py [--quick] [--inputs N] [--only NAME ...]`
(`make bench-faults` is the place for it: it is a fault campaign of the input side).

`tests/test_fuzz_parsers.py` runs a few dozen to a few hundred hypothesis examples per parser on
every `make test`; that is enough to keep fixed bugs fixed, not to say how much of a parser the
fuzzing reaches. This bench runs each parser alone for N inputs (default 3000, `--quick` 150)
with the test file's strategies and property checks, and measures with coverage.py how much of
that parser's own module(s) the inputs executed (lines and branches; the lines a module runs
when it is imported count as covered, as under pytest-cov). Coverage is what tells a weak
strategy from a robust parser: a parser at 40 % branch coverage has not been fuzzed, whatever
the number of inputs.

A finding is an exception other than the parser's documented error type, a property check of
the test file that fails (wrong output types, counters that do not add up, an internal buffer,
table or queue that grows past its bound), an error the code logs instead of raising (the MAVLink
dispatcher and command handler catch handler exceptions and log them at ERROR), or an input that
takes more than 1 s (re-run once, so a loaded machine alone does not make one; a hard limit of
10 s interrupts a real hang). Each distinct finding (kind, exception type, line) is reduced with
hypothesis to its smallest input, printed, and turned into a regression test in
tests/test_fuzz_parsers.py by hand.

Hypothesis generates fresh random inputs every run (no example database, not derandomized): a
run's figures vary a little, and a run may find what the previous one did not. The table is
printed in markdown and written to bench/results/fuzz.json.
"""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import os
import random
import shutil
import signal
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType, ModuleType
from typing import Any

import coverage
import hypothesis
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parent.parent
TESTS = ROOT / "tests"
RESULTS = ROOT / "bench" / "results"
for _p in (str(ROOT), str(TESTS)):
    if _p not in sys.path:
        sys.path.insert(0, _p)

#: the MAVLink FTP server is three modules (wire format, served tree, sessions): measured together
FTP_MODULES = ["gcs_bridge/services/ftp.py", "gcs_bridge/services/ftp_wire.py",
               "gcs_bridge/services/ftp_tree.py"]
SLOW_S = 1.0  # an input slower than this (twice) is a finding
HARD_LIMIT_S = 10.0  # an input still running after this is interrupted: a hang
DEFAULT_INPUTS = 3000
QUICK_INPUTS = 150
TARGET_BUDGET_S = 60.0  # a target that reaches this stops generating (the table says so)
REPR_CHARS = 300


# ---------------------------------------------------------------------------------------------
# Findings


class _Hang(Exception):
    """Raised by the alarm in the input that overran HARD_LIMIT_S."""


class _OutOfTime(BaseException):
    """Ends a target's hypothesis run early; a BaseException so hypothesis does not shrink it."""


@dataclass
class Finding:
    kind: str  # exception | property | logged-error | slow | hang
    signature: str  # what makes two findings the same bug
    message: str
    example: str  # repr of the first input that showed it
    count: int = 1
    minimal: str | None = None


@dataclass
class Outcome:
    """What one input did: None when all was well."""

    kind: str
    signature: str
    message: str


def _where(tb: Any) -> str:
    """file:line of the innermost frame in the project (not hypothesis, not the stdlib)."""
    best, in_bench = "?", "?"
    for frame in traceback.extract_tb(tb):
        path = Path(frame.filename)
        try:
            rel = path.resolve().relative_to(ROOT)
        except ValueError:
            continue
        if rel.parts[0] == ".venv":
            continue
        if rel.parts[0] == "bench":  # a check of the bench's own (when nothing deeper failed)
            in_bench = f"{rel}:{frame.lineno}"
        else:
            best = f"{rel}:{frame.lineno}"
    return best if best != "?" else in_bench


@contextmanager
def _alarm(limit_s: float) -> Iterator[None]:
    def fire(_sig: int, _frame: FrameType | None) -> None:
        raise _Hang(f"still running after {limit_s:g} s")

    old = signal.signal(signal.SIGALRM, fire)
    signal.setitimer(signal.ITIMER_REAL, limit_s)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


class ErrorLog(logging.Handler):
    """Collects ERROR records of the project's loggers (a caught handler bug is logged there)."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.name.split(".")[0] in ("companion", "gcs_bridge", "legacy_protocol"):
            self.records.append(record)


ERRORS = ErrorLog()


def run_one(run: Callable[[Any], None], x: Any) -> Outcome | None:
    """One input through one target, classified (see the module docstring)."""
    ERRORS.records.clear()
    try:
        with _alarm(HARD_LIMIT_S):
            run(x)
    except _Hang as exc:
        return Outcome("hang", "hang", str(exc))
    except AssertionError as exc:
        first = (str(exc).splitlines() or [""])[0][:80]
        return Outcome("property", f"AssertionError at {_where(exc.__traceback__)}",
                       first or "assertion failed")
    except Exception as exc:
        return Outcome("exception", f"{type(exc).__name__} at {_where(exc.__traceback__)}",
                       f"{type(exc).__name__}: {exc}"[:200])
    if ERRORS.records:
        rec = ERRORS.records[0]
        where = f"{Path(rec.pathname).name}:{rec.lineno}"
        text = rec.getMessage()
        if rec.exc_info and rec.exc_info[1] is not None:
            exc = rec.exc_info[1]
            where = f"{type(exc).__name__} at {_where(exc.__traceback__)}"
            text += f": {type(exc).__name__}: {exc}"
        return Outcome("logged-error", f"logged ERROR ({where})", text[:200])
    return None


def _short(x: Any) -> str:
    text = repr(x)
    return text if len(text) <= REPR_CHARS else text[:REPR_CHARS] + f"... ({len(text)} chars)"


# ---------------------------------------------------------------------------------------------
# Targets


@dataclass
class Target:
    """One parser: the module(s) whose coverage is measured, the input strategy, one run."""

    name: str
    modules: list[str]
    strategy: st.SearchStrategy[Any]
    run: Callable[[Any], None]
    cleanup: Callable[[], None] = lambda: None
    note: str = ""


@dataclass
class Result:
    name: str
    modules: list[str]
    inputs: int
    seconds: float
    line_pct: float
    branch_pct: float
    findings: list[Finding] = field(default_factory=list)
    stopped_early: bool = False


def _frame_targets(tm: ModuleType) -> list[Target]:
    """IMU fast frames, servo pilot and command frames (SyncFrameDecoder subclasses)."""
    targets = []
    for proto in tm.PROTOCOLS:
        stream = st.lists(st.one_of(tm.sync_rich_garbage(proto.sync), proto.frames),
                          max_size=12).map(b"".join)
        strategy = st.tuples(stream, st.lists(st.integers(0, 1200), max_size=20))

        def run(x: tuple[bytes, list[int]], proto: Any = proto) -> None:
            data, cuts = x
            # the same checks as test_frame_decoder_any_bytes_any_chunking
            whole, dec_whole = tm.run_chunks(proto, [data])
            pieces, dec_pieces = tm.run_chunks(proto, tm.split_at(data, cuts))
            assert pieces == whole, "chunking changed the items"
            assert dec_pieces.counters == dec_whole.counters
            c = dec_whole.counters
            assert (c.bytes_discarded + proto.frame_len * c.frames_good + len(dec_whole._buf)
                    == len(data)), "bytes not accounted for"
            # and the single-frame decoder on whatever starts the stream
            try:
                item = proto.reference(data[: proto.frame_len])
            except ValueError as exc:
                assert str(exc)
            else:
                tm.check_items(proto, [item])

        module = ("companion/drivers/imu_protocol.py" if proto.name == "imu"
                  else "companion/drivers/servo_protocol.py")
        targets.append(Target(proto.name, [module], strategy, run))
    return targets


GPS_MODULES = (
    "companion/drivers/gps_protocol.py", "companion/drivers/nmea_fields.py",
    "companion/drivers/nmea_sentences.py", "companion/drivers/ashtech_pos.py",
    "companion/drivers/gps_solution.py", "companion/drivers/gps_encoder.py",
)
"""The GPS protocol's modules (one file before it was split by job), measured together."""


def _gps_targets(tm: ModuleType) -> list[Target]:
    """NmeaDecoder on NMEA-only streams, and on streams with Ashtech $PASHR sentences."""
    from companion.drivers.gps_encoder import encode_epoch
    from companion.drivers.gps_protocol import MAX_LINE_CHARS, NmeaDecoder
    from companion.drivers.gps_solution import GpsSolution
    from companion.drivers.nmea_fields import nmea_sentence

    def bodies(addresses: list[str]) -> st.SearchStrategy[str]:
        return st.builds(lambda a, parts: ",".join([a, *parts]), st.sampled_from(addresses),
                         st.lists(tm._nmea_field, max_size=20)).filter(
            lambda b: len(b) <= MAX_LINE_CHARS - 4)

    printable = tm._PRINTABLE
    noise = [
        st.binary(max_size=60),
        st.lists(st.sampled_from(list(b"$*,.0123456789ABCDEFGNPRSTV\r\n\x00\xff")),
                 max_size=60).map(bytes),
        st.text(alphabet=printable, min_size=MAX_LINE_CHARS - 10,
                max_size=2 * MAX_LINE_CHARS).map(lambda t: b"$" + t.encode()),
    ]
    epochs = st.builds(GpsSolution, utc=st.floats(0, 86399.99), fix=st.integers(0, 3),
                       sats=st.integers(0, 40), lat_deg=st.floats(-89.9, 89.9),
                       lon_deg=st.floats(-179.9, 179.9), alt_m=st.floats(-400, 30000))
    nmea_only = [a for a in tm._ADDRESSES if not a.startswith("P")]
    pashr = ["PASHR,POS", "PASHR,ATT", "PASHR,POS", "PASHR", "P", "GPGGA", "GPRMC"]

    def strategy(addresses: list[str], with_epochs: bool) -> st.SearchStrategy[Any]:
        sentence = bodies(addresses)
        parts = [*noise, sentence.map(nmea_sentence),
                 sentence.map(lambda b: b"$" + b.encode() + b"\r\n")]
        if with_epochs:
            parts.append(epochs.map(lambda e: encode_epoch(e, ashtech_pos=True)))
        return st.tuples(
            st.lists(st.one_of(*parts), max_size=12).map(b"".join),
            st.lists(st.integers(0, 3000), max_size=20),
            st.booleans(),
            st.sampled_from([None, ["GGA"], ["GGA", "RMC", "VTG", "GSA", "GST"], ["POS"]]),
        )

    def run(x: tuple[bytes, list[int], bool, list[str] | None]) -> None:
        data, cuts, allow, expected = x
        # the checks of test_gps_decoder_any_bytes_any_chunking, with an epoch layout too
        results = []
        for chunks in ([data], tm.split_at(data, cuts)):
            decoder = NmeaDecoder(allow_no_checksum=allow, expected_sentences=expected,
                                  idle_handoff_ms=5)
            out = tm._gps_feed(decoder, chunks, 0)
            out += decoder.flush(0)
            assert decoder.flush(0) == [], "a second flush handed off an epoch again"
            for sol in out:
                tm.check_solution(sol)
            assert decoder.counters.epochs == len(out)
            results.append((out, decoder.counters, bytes(decoder._buf)))
        assert results[0] == results[1], "chunking changed what was decoded"

    module = list(GPS_MODULES)
    return [Target("gps-nmea", module, strategy(nmea_only, False), run),
            Target("gps-pashr", module, strategy(pashr, True), run)]


def _legacy_target(tm: ModuleType) -> Target:
    from legacy_protocol import codec

    inner = tm.test_legacy_decode_never_raises_and_reencodes.hypothesis.inner_test
    fleet = tm.test_legacy_monitor_fleet_folds_any_datagram.hypothesis.inner_test
    datagram = st.one_of(st.binary(max_size=200), tm.legacy_datagrams())
    source = st.sampled_from([("10.0.0.1", 5500), ("10.0.0.2", 40000)])

    def run(x: list[tuple[bytes, tuple[str, int]]]) -> None:
        for raw, _src in x:
            inner(raw=raw)
        fleet(datagrams=x)

    del codec
    return Target("legacy-udp", ["legacy_protocol/codec.py", "legacy_protocol/messages.py"],
                  st.lists(st.tuples(datagram, source), min_size=1, max_size=6), run,
                  note="codec.decode/encode, then monitor Fleet.apply")


# the log reader and the modules it reads with (framing, definitions, damage, decoding)
LOG_READER_MODULES = [
    "companion/logs/reader.py", "companion/logs/framing.py", "companion/logs/versions.py",
    "companion/logs/resync.py", "companion/logs/decode.py",
]


def _log_reader_target(tm: ModuleType, work: Path) -> Target:
    from companion.logs import read_log

    raw = tm.write_fuzz_log(work / "log-src")
    path = work / "mutated.bin"
    strategy = st.one_of(
        tm.log_mutations(raw), tm.log_mutations(raw),
        st.binary(max_size=2000),
        st.lists(st.sampled_from([b"\xbd\x00\x00\x00", b"\xed\x00\x00\x00", b"\xfd\x01\x02\x00%d",
                                  b"\xfc\x01\x01\x00n", b"\xdb\x01\x04\x00", b"\xba\x01\x03\x00",
                                  b"\x00" * 8, b"\xff"]), max_size=60).map(b"".join),
    )

    def run(data: bytes) -> None:
        tm.check_log_read(data)  # strict and salvage, the test's invariants
        path.write_bytes(data)
        read_log(path, salvage=True)  # the file entry point never raises when salvaging

    return Target("log-reader", LOG_READER_MODULES, strategy, run,
                  note="mutated LogService files and random bytes")


def _config_target(tm: ModuleType, work: Path) -> Target:
    load = tm.test_config_toml_ish_text_gives_config_or_config_error.hypothesis.inner_test
    override = tm.test_config_override_gives_config_or_config_error.hypothesis.inner_test
    folder = work / "config"
    folder.mkdir()
    text = st.one_of(st.lists(tm._toml_line, max_size=12).map("\n".join), st.text(max_size=200))
    assignment = st.one_of(
        st.text(max_size=40),
        st.tuples(st.sampled_from([*tm._SECTIONS, "", "vehicle.id.x"]), st.sampled_from(tm._KEYS),
                  st.text(max_size=20)).map(lambda t: f"{t[0]}.{t[1]}={t[2]}"),
    )

    def run(x: tuple[str, str]) -> None:
        load(tmp_path=folder, text=x[0])
        override(assignment=x[1])

    return Target("config", ["companion/core/config.py"], st.tuples(text, assignment), run,
                  note="load_config on TOML-ish text, apply_override")


def _params_file_target(tm: ModuleType, work: Path) -> Target:
    import warnings

    any_bytes = tm.test_param_file_any_bytes_gives_issues_never_exceptions.hypothesis.inner_test
    lines = tm.test_param_file_garbage_lines_do_not_hide_valid_ones.hypothesis.inner_test
    folder = work / "params"
    folder.mkdir()
    strategy = st.one_of(
        st.tuples(st.just("bytes"), st.one_of(
            st.binary(max_size=400),
            st.lists(tm._garbage_line, max_size=20).map(b"\n".join),
            st.text(max_size=300).map(str.encode))),
        st.tuples(st.just("lines"), st.tuples(
            st.tuples(st.integers(-100, 100), st.integers(-(2**31), 2**31 - 1),
                      st.floats(-10, 10, width=32), st.floats(0, 1e6, width=32)),
            st.sampled_from(["parm", "params"]),
            st.lists(st.tuples(st.integers(0, 100), tm._garbage_line), max_size=12))),
    )

    def run(x: tuple[str, Any]) -> None:
        with warnings.catch_warnings():
            # the test's filterwarnings: float32 overflow of "1e40" before the range check
            warnings.filterwarnings("ignore", "overflow encountered in cast", RuntimeWarning)
            if x[0] == "bytes":
                any_bytes(tmp_path=folder, raw=x[1])
            else:
                values, fmt, garbage = x[1]
                lines(tmp_path=folder, values=values, fmt=fmt, garbage=garbage)

    return Target("params-file", ["companion/core/params.py"], strategy, run,
                  note="parse_param_file and ParamRegistry.load")


# -- MAVLink: an in-process bridge (no threads, no sockets) ------------------------------------


class _FakeTransport:
    """Stands in for the link's UDP socket: `recv` hands out what the target queued."""

    bytes_per_s = None

    def __init__(self) -> None:
        self.pending: list[tuple[Any, bytes]] = []
        self.sent = 0

    def recv(self, _timeout_s: float) -> list[tuple[Any, bytes]]:
        out, self.pending = self.pending, []
        return out

    def send(self, frame: bytes) -> bool:
        self.sent += 1
        return True

    def accept_peer(self, peer: Any, trusted: bool) -> None:
        pass

    def open(self) -> None:
        pass

    def close(self) -> None:
        pass


class _Bridge:
    """A SyntheticVehicle's bridge, built but never started, with one fake-transport link and a
    flight directory to list, download and serve over FTP."""

    def __init__(self, tm: ModuleType, work: Path) -> None:
        from support.synthetic_vehicle import SyntheticVehicle

        flights = work / "flights"
        flight = flights / "20260101T000000Z"
        flight.mkdir(parents=True)
        (flight / "fuzz.bin").write_bytes(tm.write_fuzz_log(work / "bridge-log"))
        (flight / "run.json").write_text('{"started_utc": "2026-01-01T00:00:00"}')
        self.vehicle = SyntheticVehicle(["udpin:127.0.0.1:1"], vehicle_id=tm.VEHICLE_ID,
                                        extra_params=tm._FUZZ_PARAMS,
                                        flight_dir=flights / "current", tlog=False)
        self.bridge = self.vehicle.bridge
        self.link = self.bridge.links[0]
        self.transport = _FakeTransport()
        self.link.transport = self.transport  # type: ignore[assignment]
        self.names = [s.name for s in self.vehicle.params.specs()]

    def reset(self) -> None:
        """Forget what an earlier input set on the link (stream intervals, commands remembered
        for re-sends, the pack error count), so a finding comes from one input alone and
        hypothesis can shrink it. Parsers, peers and sessions are kept: their bounds are what
        many inputs in a row must not break."""
        from gcs_bridge.streams import StreamScheduler

        link = self.link
        link.scheduler = StreamScheduler(link.core, line_bytes_s=None,
                                         signed=link.policy.key is not None)
        link._pack_errors = 0
        self.bridge.commands._recent.clear()

    def drain(self) -> None:
        """What the sender thread would do with the answers: run them, bounded."""
        link = self.link
        for _ in range(4096):
            item = link.queue.get_nowait()
            if item is None:
                break
            link.run_item(item)
        for _ in range(64):
            if link.param_list_step(100) >= 1 << 62:
                break
        for _ in range(64):
            if not link.bulk.busy():
                break
            link.bulk.step(time.monotonic_ns() + 10**12, link.emit)

    def check_bounds(self) -> None:
        link = self.link
        assert len(link._parsers) <= 32, f"{len(link._parsers)} parsers"
        assert len(link.peers) <= 32, f"{len(link.peers)} peers"
        assert len(link.heard) <= 4 * 32, f"{len(link.heard)} heard peers"
        assert len(self.bridge.commands._recent) <= 256
        assert len(link.services.ftp._sessions) <= 4
        assert len(link.queue) == 0, "answers left queued after draining"
        assert link._pack_errors == 0, "an answer could not be packed"

    def close(self) -> None:
        self.link.services.close()
        self.bridge.close()


def _mavlink_targets(tm: ModuleType, work: Path) -> list[Target]:
    from gcs_bridge.dialect import mavlink
    from gcs_bridge.services import ftp as ftp_mod
    from gcs_bridge.services import ftp_wire
    from gcs_bridge.services.log_download import LogServer

    b = _Bridge(tm, work)
    names = b.names
    m = mavlink
    peers = st.sampled_from([("10.0.0.1", 14550), ("10.0.0.2", 14551)])

    # 1. the dispatcher: datagrams of whole frames (hypothesis-chosen messages), damaged bytes
    datagrams = st.lists(st.tuples(peers, st.one_of(tm.frames_from(names), tm.frames_from(names),
                                                    tm.damaged_bytes(names))),
                         min_size=1, max_size=6)

    def run_dispatch(x: list[tuple[tuple[str, int], bytes]]) -> None:
        b.reset()
        for peer, data in x:
            b.transport.pending.append((peer, data))
            b.link.receive(0.0)
            b.drain()
        b.check_bounds()

    # 2. the parameter protocol, called as the dispatcher calls it
    param_id = st.one_of(st.sampled_from(names), st.text(max_size=17),
                         st.binary(max_size=16).map(lambda r: r.decode("latin-1")))

    def run_params(x: tuple[str, bytes, int, bool, int]) -> None:
        pid, raw, mav_type, bytewise, index = x
        proto = b.bridge.params
        found = proto.lookup(pid, index)
        assert found is None or 0 <= found < proto.count()
        out = proto.apply_set(pid, raw, mav_type, bytewise=bytewise)
        assert isinstance(out.ok, bool) and isinstance(out.reason, str)
        assert out.ok or (out.reason and 0 < out.error < 256), out
        if out.index is not None:
            msg = proto.value_message(out.index, bytewise=bytewise)
            assert msg is not None
            msg.pack(mavlink.MAVLink(None, 1, 1))  # what is sent back can be sent
        tm.check_param_decode(raw, mav_type, bytewise)

    params_strategy = st.tuples(param_id, st.binary(max_size=8),
                                st.one_of(st.integers(1, 10), st.integers(0, 255)),
                                st.booleans(), st.integers(-(2**15), 2**15 - 1))

    # 3. COMMAND_LONG / COMMAND_INT through the command handler, every one acknowledged once
    def command_frames(msgname: str) -> st.SearchStrategy[bytes]:
        cls = getattr(m, f"MAVLink_{msgname.lower()}_message")
        fields = {}
        for fname, ftype in zip(cls.fieldnames, cls.fieldtypes, strict=True):
            if ftype == "float":
                fields[fname] = st.one_of(st.integers(-2, 400).map(float), st.floats(width=32))
            else:
                fields[fname] = tm._scalar(msgname, fname, ftype)
        return st.fixed_dictionaries(fields).map(
            lambda kw: cls(**kw).pack(mavlink.MAVLink(None, 255, 190)))

    disruptive = {int(m.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN), int(m.MAV_CMD_USER_1)}

    def run_commands(frames: list[bytes]) -> None:
        b.reset()
        parser = mavlink.MAVLink(None, 0, 0)
        for frame in frames:
            msgs = parser.parse_buffer(frame) or []
            for msg in msgs:
                b.bridge.commands.handle(b.link, msg)
                acks = 0
                while (item := b.link.queue.get_nowait()) is not None:
                    if isinstance(item, list):
                        acks += sum(x.get_type() == "COMMAND_ACK" for x in item)
                    b.link.run_item(item)
                if int(msg.command) not in disruptive:
                    assert acks == 1, f"command {msg.command}: {acks} COMMAND_ACK"
                else:
                    assert acks <= 1
        assert len(b.bridge.commands._recent) <= 256
        assert b.link._pack_errors == 0, "an answer could not be packed"

    def interval_pair(msg_id: float, interval: float, request: bool) -> bytes:
        """SET_MESSAGE_INTERVAL then its read-back (GET_MESSAGE_INTERVAL or REQUEST_MESSAGE
        MESSAGE_INTERVAL): what one input needs to reach the answer of a stored interval."""
        mav = mavlink.MAVLink(None, 255, 190)
        put = m.MAVLink_command_long_message(1, 1, int(m.MAV_CMD_SET_MESSAGE_INTERVAL), 0,
                                             msg_id, interval, 0, 0, 0, 0, 0)
        get = (m.MAVLink_command_long_message(1, 1, int(m.MAV_CMD_REQUEST_MESSAGE), 0,
                                              float(m.MAVLINK_MSG_ID_MESSAGE_INTERVAL), msg_id,
                                              0, 0, 0, 0, 0) if request else
               m.MAVLink_command_long_message(1, 1, int(m.MAV_CMD_GET_MESSAGE_INTERVAL), 0,
                                              msg_id, 0, 0, 0, 0, 0, 0))
        return put.pack(mav) + get.pack(mav)

    pairs = st.builds(interval_pair,
                      st.sampled_from([0.0, 24.0, 30.0, 31.0, 33.0, 65.0, 74.0, 105.0, 147.0]),
                      st.one_of(st.integers(-2, 10**6).map(float), st.floats(width=32)),
                      st.booleans())
    commands_strategy = st.lists(st.one_of(command_frames("COMMAND_LONG"),
                                           command_frames("COMMAND_INT"), pairs),
                                 min_size=1, max_size=4)

    # 4. the FTP server on request payloads (sequences, so sessions open, read and write)
    ftp_root = work / "ftp"
    ops = [ftp_wire.OP_NONE, ftp_wire.OP_TERMINATE_SESSION, ftp_wire.OP_RESET_SESSIONS,
           ftp_wire.OP_LIST_DIRECTORY, ftp_wire.OP_LIST_DIRECTORY_WITH_TIME, ftp_wire.OP_OPEN_FILE_RO,
           ftp_wire.OP_READ_FILE, ftp_wire.OP_BURST_READ_FILE, ftp_wire.OP_CALC_FILE_CRC32,
           ftp_wire.OP_CREATE_FILE, ftp_wire.OP_OPEN_FILE_WO, ftp_wire.OP_WRITE_FILE,
           ftp_wire.OP_REMOVE_FILE, ftp_wire.OP_CREATE_DIRECTORY, ftp_wire.OP_REMOVE_DIRECTORY,
           ftp_wire.OP_RENAME, ftp_wire.OP_TRUNCATE_FILE, ftp_wire.OP_ACK, ftp_wire.OP_NAK]
    path_bytes = st.one_of(
        st.sampled_from([b"", b"/", b".", b"..", b"/a.bin", b"a.bin", b"d", b"d/b.txt", b"/d/",
                         b"../x", b"/../../etc/passwd", b"d/../a.bin", b"new", b"d/new",
                         b"/@meta/general.json", b"a.bin\x00junk", b"a.bin\x00d/b.txt\x00",
                         b"\x00", b"//a.bin", b"d//b.txt", b"." * 300, b"\xff\xfe"]),
        st.binary(max_size=239),
    )
    request = st.builds(
        lambda seq, session, opcode, size, offset, data, cut: (
            ftp_wire.HEADER.pack(seq, session, opcode, min(size, 255), 0, 0, 0, offset)
            + data)[:cut],
        st.integers(0, 0xFFFF), st.one_of(st.integers(0, 3), st.integers(0, 255)),
        st.one_of(st.sampled_from(ops), st.integers(0, 255)),
        st.one_of(st.integers(0, 30), st.integers(0, 255)),
        st.one_of(st.sampled_from([0, 1, 100, 239, 0xFFFFFFFF]), st.integers(0, 0xFFFFFFFF)),
        path_bytes, st.integers(0, 260),
    )

    def fresh_ftp_root() -> None:
        shutil.rmtree(ftp_root, ignore_errors=True)
        (ftp_root / "d" / "sub").mkdir(parents=True)
        (ftp_root / "a.bin").write_bytes(bytes(range(256)) * 5)
        (ftp_root / "d" / "b.txt").write_bytes(b"hello\n")
        (ftp_root / "empty").write_bytes(b"")

    def run_ftp(x: tuple[bool, list[bytes]]) -> None:
        may_write, payloads = x
        fresh_ftp_root()
        server = ftp_mod.FtpServer(ftp_root, virtual={"/@meta/general.json": lambda: b"{}" * 300},
                                   protected=lambda: ftp_root / "d" / "sub")
        try:
            for payload in payloads:
                replies = 0
                for reply in server.handle(payload, may_write=may_write):
                    replies += 1
                    assert reply is None or (isinstance(reply, bytes)
                                             and len(reply) == ftp_wire.PAYLOAD_LEN)
                    assert replies < 10_000, "a request that never ends"
                assert len(server._sessions) <= 4
                assert all(len(q) <= 16 for q in server._answered.values())
                assert len(server._answered) <= 256, f"{len(server._answered)} answer memories"
        finally:
            server.close()

    ftp_strategy = st.tuples(st.booleans(), st.lists(request, min_size=1, max_size=8))

    # 5. the log server: list and data requests, and the run.json it reads a start time from
    log_root = work / "logserver"
    flight = log_root / "flight-a"
    flight.mkdir(parents=True)
    (flight / "fuzz.bin").write_bytes(tm.write_fuzz_log(work / "logserver-src"))
    (log_root / "20260102T030405Z").mkdir()
    (log_root / "20260102T030405Z" / "x.csv").write_text("a,b\n1,2\n")
    run_json = st.one_of(
        st.builds(lambda v: json.dumps({"started_utc": v}),
                  st.one_of(st.sampled_from(["2026-01-01T00:00:00", "2026-01-01T00:00:00+01:00",
                                             "0001-01-01T00:00:00+14:00", "9999-12-31T23:59:59",
                                             "9999-12-31T23:59:59-14:00", "", "x"]),
                            st.datetimes().map(lambda d: d.isoformat()),
                            st.text(max_size=30), st.integers(), st.floats(), st.none())),
        st.text(max_size=60), st.binary(max_size=60).map(lambda r: r.decode("latin-1")),
    )
    u16 = st.one_of(st.sampled_from([0, 1, 2, 0xFFFE, 0xFFFF]), st.integers(0, 0xFFFF))
    u32 = st.one_of(st.sampled_from([0, 1, 89, 90, 91, 4140, 0xFFFFFFFF]),
                    st.integers(0, 0xFFFFFFFF))
    log_request = st.one_of(st.tuples(st.just("list"), u16, u16),
                            st.tuples(st.just("data"), u16, u32, u32))

    def run_logserver(x: tuple[str, int, list[tuple[Any, ...]]]) -> None:
        text, first_id, requests = x
        (flight / "run.json").write_text(text, encoding="utf-8", errors="surrogatepass")
        server = LogServer(log_root, lambda: None, first_id=first_id)
        for req in requests:
            if req[0] == "list":
                entries = list(server.request_list(req[1], req[2]))
                assert len(entries) <= 3
                for e in entries:
                    e.pack(mavlink.MAVLink(None, 1, 1))
            else:
                n = 0
                for msg in server.request_data(req[1], req[2], req[3]):
                    n += 1
                    assert n < 10_000, "LOG_DATA that never ends"
                    if msg is not None:
                        assert msg.count <= 90 and msg.id == req[1]
                        msg.pack(mavlink.MAVLink(None, 1, 1))

    log_strategy = st.tuples(run_json, st.sampled_from([0, 1]),
                             st.lists(log_request, min_size=1, max_size=5))

    dispatch_modules = ["gcs_bridge/dispatch.py", "gcs_bridge/services/link_services.py"]
    return [
        Target("mavlink-dispatch", dispatch_modules, datagrams, run_dispatch, b.close,
               note="Link.receive -> Dispatcher -> handlers, answers drained"),
        Target("param-protocol", ["gcs_bridge/params/protocol.py", "gcs_bridge/params/codec.py"],
               params_strategy, run_params),
        Target("commands", ["gcs_bridge/commands.py"], commands_strategy, run_commands),
        Target("ftp-server", FTP_MODULES, ftp_strategy, run_ftp),
        Target("log-server", ["gcs_bridge/services/log_download.py"], log_strategy, run_logserver),
    ]


ALL_MODULES = [
    "companion/drivers/imu_protocol.py", "companion/drivers/servo_protocol.py",
    *GPS_MODULES, "legacy_protocol/codec.py", "legacy_protocol/messages.py",
    *LOG_READER_MODULES,
    "companion/core/config.py", "companion/core/params.py", "gcs_bridge/dispatch.py",
    "gcs_bridge/services/link_services.py", "gcs_bridge/params/protocol.py",
    "gcs_bridge/params/codec.py", "gcs_bridge/commands.py", *FTP_MODULES,
    "gcs_bridge/services/log_download.py",
]


def build_targets(work: Path) -> list[Target]:
    tm = importlib.import_module("test_fuzz_parsers")
    return [
        *_frame_targets(tm), *_gps_targets(tm), _legacy_target(tm),
        *_mavlink_targets(tm, work), _log_reader_target(tm, work), _config_target(tm, work),
        _params_file_target(tm, work),
    ]


# ---------------------------------------------------------------------------------------------
# Running and measuring


def _coverage(paths: Sequence[str]) -> coverage.Coverage:
    return coverage.Coverage(branch=True, data_file=None, include=[str(ROOT / p) for p in paths],
                             messages=False)


def _percentages(cov: coverage.Coverage, paths: Sequence[str], work: Path) -> tuple[float, float]:
    out = work / "cov.json"
    cov.json_report(morfs=[str(ROOT / p) for p in paths], outfile=str(out))
    totals = json.loads(out.read_text())["totals"]
    lines = 100.0 * totals["covered_lines"] / max(1, totals["num_statements"])
    branches = 100.0 * totals["covered_branches"] / max(1, totals["num_branches"])
    return lines, branches


class _NewFinding(Exception):
    """Raised for the first input of a new finding, so hypothesis shrinks that very input."""


def _raise_new(signature: str) -> None:
    """The one place _NewFinding is raised: hypothesis tells bugs apart by where the exception
    comes from, so the first raise and the shrinker's must come from the same line."""
    raise _NewFinding(signature)


def fuzz(target: Target, n: int, work: Path, import_data: coverage.CoverageData,
         minimize: bool, base_seed: int) -> Result:
    """Run `n` inputs through `target` under coverage. A new finding stops the run while
    hypothesis shrinks it (its smallest input is what the shrinker tried last), then the run
    goes on with the inputs left; inputs tried while shrinking are neither counted nor measured.
    """
    findings: dict[str, Finding] = {}
    count = [0]
    shrinking: list[str] = []  # the signature being shrunk, if any
    smallest: list[Any] = []
    cov = _coverage(target.modules)
    t0 = time.monotonic()

    def measured(x: Any) -> None:
        # around the parser only (5 us a pair), not the strategies' encoders nor the shrinker;
        # one call line either way, since a finding's signature names the frames
        tracing = not shrinking
        if tracing:
            cov.start()
        try:
            target.run(x)
        finally:
            if tracing:
                cov.stop()

    def guarded(x: Any) -> None:
        if shrinking:
            outcome = run_one(measured, x)
            if outcome is not None and outcome.signature == shrinking[0]:
                smallest[:] = [x]
                _raise_new(outcome.signature)
            return
        if time.monotonic() - t0 > TARGET_BUDGET_S:
            raise _OutOfTime
        count[0] += 1
        start = time.perf_counter()
        outcome = run_one(measured, x)
        if outcome is None and time.perf_counter() - start > SLOW_S:
            start = time.perf_counter()  # once more: a loaded machine alone is no finding
            outcome = run_one(target.run, x)
            took = time.perf_counter() - start
            if outcome is None and took > SLOW_S:
                outcome = Outcome("slow", "slow input", f"{took:.2f} s (twice over {SLOW_S} s)")
        if outcome is None:
            return
        known = findings.get(outcome.signature)
        if known is not None:
            known.count += 1
            return
        findings[outcome.signature] = Finding(outcome.kind, outcome.signature, outcome.message,
                                              _short(x))
        if minimize and outcome.kind != "slow":
            shrinking[:] = [outcome.signature]
            smallest[:] = [x]
            _raise_new(outcome.signature)

    stopped = False
    rounds = 0
    while count[0] < n and not stopped:
        rounds += 1

        @hypothesis.seed(base_seed + rounds)
        @settings(max_examples=n - count[0], database=None, deadline=None,
                  derandomize=False, suppress_health_check=list(HealthCheck),
                  phases=[Phase.generate, Phase.shrink], report_multiple_bugs=False)
        @given(target.strategy)
        def loop(x: Any) -> None:
            guarded(x)

        try:
            loop()
            break
        except _OutOfTime:
            stopped = True
        except _NewFinding as exc:
            findings[str(exc)].minimal = _short(smallest[0]) if smallest else None
        except Exception:  # (hypothesis could not replay it: a flaky finding) not shrunk
            pass
        finally:
            shrinking.clear()
    seconds = time.monotonic() - t0
    cov.get_data().update(import_data)
    line_pct, branch_pct = _percentages(cov, target.modules, work)
    return Result(target.name, target.modules, count[0], seconds, line_pct, branch_pct,
                  list(findings.values()), stopped)


def _table(results: Sequence[Result]) -> str:
    rows = ["| parser | module(s) | inputs | time | line cov. | branch cov. | findings |",
            "|---|---|---:|---:|---:|---:|---|"]
    for r in results:
        found = "; ".join(f"{f.kind}: {f.signature} (x{f.count})" for f in r.findings) or "none"
        mods = ", ".join(m.split("/", 1)[1] if "/" in m else m for m in r.modules)
        note = " (time budget)" if r.stopped_early else ""
        rows.append(f"| {r.name} | {mods} | {r.inputs}{note} | {r.seconds:.1f} s | "
                    f"{r.line_pct:.0f} % | {r.branch_pct:.0f} % | {found} |")
    return "\n".join(rows)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inputs", type=int, default=None,
                    help=f"inputs per parser (default {DEFAULT_INPUTS}, --quick {QUICK_INPUTS})")
    ap.add_argument("--quick", action="store_true", help="a short smoke run")
    ap.add_argument("--only", nargs="*", default=[], help="only these parsers (table names)")
    ap.add_argument("--no-minimize", action="store_true",
                    help="report findings without reducing them to a smallest input")
    ap.add_argument("--seed", type=int, default=None,
                    help="hypothesis seed (default: a fresh random one, printed with the table)")
    ap.add_argument("--json", type=Path, default=None,
                    help="where to write the table as JSON (default bench/results/fuzz.json "
                         "when bench/results exists)")
    args = ap.parse_args(argv)
    n = args.inputs or (QUICK_INPUTS if args.quick else DEFAULT_INPUTS)
    run_seed = args.seed if args.seed is not None else random.getrandbits(32)

    logging.getLogger().addHandler(ERRORS)
    logging.getLogger().setLevel(logging.ERROR)
    work = Path(tempfile.mkdtemp(prefix="fuzz-bench-"))
    t_all = time.monotonic()
    try:
        # the parsers' modules are imported under coverage, so their import-time lines count
        import_cov = _coverage(ALL_MODULES)
        import_cov.start()
        try:
            targets = build_targets(work)
        finally:
            import_cov.stop()
        import_data = import_cov.get_data()
        known = [t.name for t in targets]
        unknown = sorted(set(args.only) - set(known))
        if unknown:
            print(f"fuzz_bench: unknown parser(s) {unknown}; choose from {known}",
                  file=sys.stderr)
            return 2
        results = []
        for target in targets:
            if args.only and target.name not in args.only:
                continue
            r = fuzz(target, n, work, import_data, not args.no_minimize, run_seed)
            results.append(r)
            print(f"{r.name}: {r.inputs} inputs, {r.seconds:.1f} s, lines {r.line_pct:.0f} %, "
                  f"branches {r.branch_pct:.0f} %, {len(r.findings)} finding(s)",
                  file=sys.stderr, flush=True)
        for target in targets:
            target.cleanup()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    wall = time.monotonic() - t_all

    one, five, _ = os.getloadavg()
    print(f"## Fuzzing: {n} hypothesis inputs per parser, line and branch coverage of its "
          f"module(s)\n")
    print(f"`python bench/fuzz_bench.py{' --quick' if args.quick else ''}"
          f"{f' --inputs {args.inputs}' if args.inputs else ''}`: {wall:.0f} s wall, load "
          f"average {one:.2f} (1 min) {five:.2f} (5 min) on {os.cpu_count()} CPUs, hypothesis "
          f"seed {run_seed} (`--seed {run_seed}` generates the same inputs), coverage.py "
          f"{coverage.__version__}.\n")
    print(_table(results))
    all_findings = [(r.name, f) for r in results for f in r.findings]
    if all_findings:
        print("\n### Findings\n")
        for name, f in all_findings:
            print(f"- **{name}**, {f.kind}: {f.signature}: {f.message}\n"
                  f"  - first input: `{f.example}`\n"
                  f"  - smallest input: `{f.minimal if f.minimal is not None else 'n/a'}`")
    target_json = args.json or (RESULTS / "fuzz.json" if RESULTS.is_dir() else None)
    if target_json is not None:
        target_json.write_text(json.dumps({
            "command": " ".join(["python", "bench/fuzz_bench.py", *(argv or sys.argv[1:])]),
            "inputs_per_parser": n,
            "seed": run_seed,
            "wall_s": round(wall, 1),
            "load_average_1_5": [round(one, 2), round(five, 2)],
            "cpus": os.cpu_count(),
            "coverage_version": coverage.__version__,
            "results": [{
                "parser": r.name, "modules": r.modules, "inputs": r.inputs,
                "stopped_by_time_budget": r.stopped_early, "seconds": round(r.seconds, 2),
                "line_coverage_pct": round(r.line_pct, 1),
                "branch_coverage_pct": round(r.branch_pct, 1),
                "findings": [vars(f) for f in r.findings],
            } for r in results],
        }, indent=2) + "\n")
        print(f"\n(written to {target_json.relative_to(ROOT) if target_json.is_relative_to(ROOT) else target_json})")
    return 1 if all_findings else 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from bench.result import run_captured

    sys.exit(run_captured("fuzz", ["companion", "gcs_bridge", "legacy_protocol"], main))
