"""Faults injected into the runtime's own threads during a SITL flight (`--thread-fault`).

The world injects faults into the devices' bytes and ports (`--fault`, `--vanish`); this injects
them into the code (the kinds and their syntax are the fault catalogue's, `companion.sim.faults`): at a given flight time, a thread's `step` starts misbehaving in one of the ways the
supervisor is built to survive, so the fault campaign can measure what the aircraft does and what
it is told, in a real flight rather than in a unit test:

- `raise`: the next step raises (a crash: restarted once);
- `crash-loop`: every step raises (restart intensity exceeded: the thread is left down);
- `pyloop`: the next step loops in Python ignoring its stop event (interrupted, restarted);
- `cblock`: the next step blocks inside C for an hour (abandoned, replaced);
- `alloc`: every step keeps 1 MiB more, for 10 s of flight time (nothing bounds a thread's
  memory: this measures it).

Injected through `RuntimeOptions.extra_bridges`, like the live view: the runtime knows nothing of it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from companion.sim.faults import ThreadFault
from companion.watchdog import RuntimeContext, ThreadManager

log = logging.getLogger(__name__)

__all__ = ["ThreadFaultInjector"]

ALLOC_CHUNK = 1 << 20
ALLOC_FOR_S = 10.0


class ThreadFaultInjector:
    """Arms each fault from a manager tick once its time has come (a `Bridge`: close, stats)."""

    def __init__(self, ctx: RuntimeContext, manager: ThreadManager,
                 faults: list[ThreadFault]) -> None:
        for f in faults:
            if manager.find(f.thread) is None:
                names = ", ".join(t.name for t in manager.threads)
                raise ValueError(f"--thread-fault {f.thread}:{f.kind}: no thread {f.thread!r} "
                                 f"(threads: {names})")
        self.ctx = ctx
        self.manager = manager
        self.pending = sorted(faults, key=lambda f: f.at_s)
        self.armed: list[dict[str, Any]] = []
        self.hoard: list[bytearray] = []
        self._t0_ns = ctx.clock.monotonic_ns()
        manager.on_tick.append(self._tick)

    def _tick(self) -> None:
        elapsed_s = (self.ctx.clock.monotonic_ns() - self._t0_ns) / 1e9
        while self.pending and self.pending[0].at_s <= elapsed_s:
            self._arm(self.pending.pop(0))

    def _arm(self, fault: ThreadFault) -> None:
        thread = self.manager.find(fault.thread)
        assert thread is not None
        original: Callable[[], Any] = thread.step
        clock = self.ctx.clock
        fired = [False]
        until_ns = clock.monotonic_ns() + int(ALLOC_FOR_S * 1e9)
        kind = fault.kind

        def faulty() -> Any:
            if kind == "crash-loop":
                raise RuntimeError("injected fault: every step raises")
            if kind == "alloc":
                if clock.monotonic_ns() < until_ns:
                    self.hoard.append(bytearray(ALLOC_CHUNK))
                return original()
            if fired[0]:
                return original()
            fired[0] = True
            if kind == "raise":
                raise RuntimeError("injected fault: one step raises")
            if kind == "pyloop":
                while True:  # ignores its stop event: only an asynchronous exception ends it
                    pass
            if kind == "cblock":
                time.sleep(3600)  # inside C, the interpreter lock released: nothing ends it
            return original()

        thread.step = faulty  # type: ignore[method-assign]
        self.armed.append({"thread": fault.thread, "kind": kind, "at_s": fault.at_s,
                           "t_ns": clock.realtime_ns()})
        log.warning("injected %s into thread %s", kind, fault.thread)

    def close(self) -> None:
        self.hoard.clear()

    def stats(self) -> list[dict[str, Any]]:
        return []

