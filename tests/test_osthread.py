"""Managed threads carry their names at the OS level (`top -H`, `ps -L`, the SITL benchmark)."""

from __future__ import annotations

import sys
import threading
from pathlib import Path

import pytest
from conftest import wait_for

from companion.core.clock import Clock
from companion.core.osthread import set_native_name
from companion.core.params import ParamRegistry
from companion.watchdog import ManagedThread, RuntimeContext, ThreadManager

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux thread names")


def _comm(native_id: int) -> str:
    return Path(f"/proc/self/task/{native_id}/comm").read_text().strip()


def test_set_native_name_truncates_to_the_kernel_limit() -> None:
    seen: list[str] = []

    def body() -> None:
        assert set_native_name("a-rather-long-thread-name")
        seen.append(_comm(threading.get_native_id()))

    t = threading.Thread(target=body)
    t.start()
    t.join(5)
    assert seen == ["a-rather-long-t"]


class _Idle(ManagedThread):
    def step(self) -> bool:
        self.stop_event.wait(0.01)
        return True


def test_a_managed_thread_is_named_for_the_os() -> None:
    thread = _Idle("estimator", thread_id=1, period_ms=10.0, watchdog_ms=1000)
    ctx = RuntimeContext(clock=Clock(), params=ParamRegistry())
    mgr = ThreadManager(ctx, [thread])
    mgr.start()
    try:
        assert wait_for(lambda: thread.in_periodic, 5.0)
        names = {_comm(int(p.name)) for p in Path("/proc/self/task").iterdir()}
        assert "estimator" in names
    finally:
        mgr.request_stop()
        mgr.shutdown()
