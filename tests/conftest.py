"""Shared fixtures: every test must leave no thread, file descriptor or socket behind."""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

# Everything the tests read is in tests/data (see tests/data/README.md for where each file came
# from). A missing file is a failure with the path in the message, never a skip: a test that
# silently skips would leave the claim it checks untested on the machine that lacks the file.
DATA = Path(__file__).resolve().parent / "data"
VECTORS = DATA / "vectors"
HORIZON_DEV = DATA / "horizon-dev"


def data_file(*parts: str) -> Path:
    """Path of a file under tests/data, or a test failure naming the file that is missing."""
    path = DATA.joinpath(*parts)
    if not path.is_file():
        pytest.fail(f"test data missing: {path.relative_to(DATA.parent.parent)} "
                    "(it is tracked in git: restore it with `git checkout -- tests/data`)",
                    pytrace=False)
    return path


def _fds() -> set[int]:
    """Open file descriptors, without the one used to list them (which takes the lowest free
    number, so it could otherwise show up as a "leak" that is already closed)."""
    try:
        fd = os.open("/proc/self/fd", os.O_RDONLY | os.O_DIRECTORY)
    except OSError:
        return set()
    try:
        return {int(x) for x in os.listdir(fd)} - {fd}
    finally:
        os.close(fd)


# Peer programs the repository does not hold (a real autopilot, a MAVLink router): tests marked
# with one of these markers run only when the environment variable names an executable file (`make
# test` and .ci/run set them from the sibling tools directory when it is there; README: "Testing
# against a real autopilot"). Without it they are deselected, with one line saying how many and
# why: never a silent skip, and never a download.
PEER_TOOLS = {
    "sitl": ("ARDUPILOT_SITL", "the ArduPlane SITL"),
    "router": ("MAVLINK_ROUTER", "mavlink-router"),
}


def peer_tool(marker: str) -> str | None:
    """The path the marker's environment variable names, when it is an executable file."""
    value = os.environ.get(PEER_TOOLS[marker][0], "")
    return value if value and os.path.isfile(value) and os.access(value, os.X_OK) else None


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "allow_leaks: the test knowingly leaves threads behind")
    for marker, (var, what) in PEER_TOOLS.items():
        config.addinivalue_line("markers", f"{marker}: needs {what} ({var}=PATH)")


_deselected_for: dict[str, int] = {}


@pytest.hookimpl(trylast=True)  # after -k and -m: count only what would have run
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    _deselected_for.clear()
    missing = [marker for marker in PEER_TOOLS if peer_tool(marker) is None]
    if not missing:
        return
    keep, drop = [], []
    for item in items:
        lacking = [m for m in missing if item.get_closest_marker(m) is not None]
        if lacking:
            drop.append(item)
            _deselected_for[lacking[0]] = _deselected_for.get(lacking[0], 0) + 1
        else:
            keep.append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep


def pytest_report_collectionfinish(config: pytest.Config) -> list[str]:
    lines = []
    for marker, count in _deselected_for.items():
        var, what = PEER_TOOLS[marker]
        need, were = ("test needs", "was") if count == 1 else ("tests need", "were")
        value = os.environ.get(var, "")
        wrong = f"; {var}={value!r} is not an executable file" if value else ""
        lines.append(f"{count} {need} {what} and {were} deselected: set {var}=PATH "
                     f"(see README: Testing against a real autopilot){wrong}")
    return lines


@pytest.fixture(autouse=True)
def no_service_manager(monkeypatch: pytest.MonkeyPatch) -> None:
    """Tests run the same under a service manager (a CI runner's unit) as in a shell: its
    notification socket is not the runtime's to talk to (tests that want one set their own)."""
    for name in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID"):
        monkeypatch.delenv(name, raising=False)


@pytest.fixture(autouse=True)
def no_leaks(request: pytest.FixtureRequest) -> Iterator[None]:
    threads_before = set(threading.enumerate())
    fds_before = _fds()
    yield
    if request.node.get_closest_marker("allow_leaks"):
        return
    deadline = time.monotonic() + 5.0
    while True:
        extra_threads = [t for t in threading.enumerate() if t not in threads_before and t.is_alive()]
        extra_fds = _fds() - fds_before
        if not extra_threads and not extra_fds:
            return
        if time.monotonic() > deadline:
            break
        time.sleep(0.02)
    details = []
    for fd in sorted(extra_fds):
        try:
            details.append(f"fd {fd} -> {os.readlink(f'/proc/self/fd/{fd}')}")
        except OSError:
            details.append(f"fd {fd}")
    pytest.fail(f"leaked threads {[t.name for t in extra_threads]} fds {details}")


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_for(predicate, timeout_s: float, interval_s: float = 0.005) -> bool:  # type: ignore[no-untyped-def]
    """Poll `predicate` until true or timeout; returns its last truth value."""
    deadline = time.monotonic() + timeout_s
    while True:
        if predicate():
            return True
        if time.monotonic() > deadline:
            return bool(predicate())
        time.sleep(interval_s)


@contextlib.contextmanager
def quiet_mavsdk() -> Iterator[None]:
    """MAVSDK prints every retry; route it to logging so pytest shows it for failures only."""
    from mavsdk import log_subscribe, log_unsubscribe  # only the MAVSDK tests pay for the import

    mlog = logging.getLogger("mavsdk")

    def forward(level: Any, message: str, file: str | None, line: int) -> bool:
        mlog.debug("%s %s (%s:%s)", level.name, message, file, line)
        return True

    log_subscribe(forward)
    try:
        yield
    finally:
        log_unsubscribe()
