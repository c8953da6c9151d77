"""How a running campaign tells its user where it is, and the table it ends with.

On a terminal: one bar (rich's) with flights done / failed / running, simulated seconds flown
per host second and the time left. Anywhere else (a log file, CI, a Slurm job's output): one
plain line per event, which greps and tails well. At the end a table of what happened, the
same on both: flights, failures with their reasons, restarts, the slowest flights.
"""

from __future__ import annotations

import sys
import threading
import time
from typing import IO, Any

__all__ = ["CampaignProgress", "final_table"]

SLOWEST_SHOWN = 3


class CampaignProgress:
    """Receives the executors' events (thread-safe) and shows them."""

    def __init__(self, total: int, already_done: int, *, stream: IO[str] | None = None,
                 terminal: bool | None = None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.terminal = self.stream.isatty() if terminal is None else terminal
        self.total = total
        self.done = already_done
        self.failed = 0
        self.running: dict[int, str] = {}
        self.sim_s = 0.0
        self.t0 = time.monotonic()
        self._flown_now = 0
        self._lock = threading.Lock()
        self._bar: Any = None
        self._task: Any = None
        if self.terminal:
            from rich.console import Console
            from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

            self._bar = Progress(TextColumn("campaign"), BarColumn(),
                                 TextColumn("{task.fields[status]}"), TimeRemainingColumn(),
                                 console=Console(file=self.stream), transient=False)
            self._task = self._bar.add_task("campaign", total=total, completed=already_done,
                                            status=self._status())
            self._bar.start()

    def _status(self) -> str:
        elapsed = max(time.monotonic() - self.t0, 1e-9)
        return (f"{self.done}/{self.total} done, {self.failed} failed, {len(self.running)} "
                f"running, {self.sim_s / elapsed:.1f} sim s/s")

    def _left_s(self) -> float | None:
        if self._flown_now == 0:
            return None
        per_flight = (time.monotonic() - self.t0) / self._flown_now
        return per_flight * (self.total - self.done - self.failed)

    def event(self, kind: str, job: Any, details: dict[str, Any]) -> None:
        with self._lock:
            if kind == "recorded":  # flown by an earlier run of the campaign
                if details.get("exit_code") == 0:
                    self.done += 1
                else:
                    self.failed += 1
                if self._bar is not None:
                    self._bar.update(self._task, completed=self.done + self.failed)
                return
            if kind == "start":
                self.running[job.index] = str(details.get("node"))
                line = f"flight {job.index} started on node {details.get('node')}"
            elif kind == "retry":
                self.running.pop(job.index, None)
                line = f"flight {job.index}: {details.get('reason')}; flying it again"
            else:
                self.running.pop(job.index, None)
                self._flown_now += 1
                ok = details.get("exit_code") == 0
                if ok:
                    self.done += 1
                    self.sim_s += float(details.get("sim_s") or 0.0)
                else:
                    self.failed += 1
                state = "ok" if ok else f"FAILED ({details.get('error')})"
                line = (f"[{self.done + self.failed}/{self.total}] flight {job.index}: {state}, "
                        f"{details.get('wall_s')} s on {details.get('node')}, try "
                        f"{details.get('tries')}, {details.get('restarts')} restarts")
            if self._bar is not None:
                self._bar.update(self._task, completed=self.done + self.failed,
                                 status=self._status())
            else:
                left = self._left_s()
                tail = f"; {self._status()}" + (f", ~{left:.0f} s left" if left else "")
                print(line + tail, file=self.stream, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()


def final_table(result: dict[str, Any]) -> str:
    """The end-of-campaign table, plain text (the same on a terminal and in a log)."""
    runs = result["runs"]
    lines = [f"flights   {result['flights']}  ok {result['ok']}  failed {result['failed']}  "
             f"flown now {result['flown_now']}  restarts {result['restarts']}  "
             f"retried {sum(1 for r in runs if (r.get('tries') or 0) > 1)}",
             f"wall      {result['wall_s']} s  ({result['speed']} simulated s per s, "
             f"executor {result['executor']}, {result['slots']} at a time)"]
    failed = [r for r in runs if r.get("exit_code") != 0]
    if failed:
        lines.append("failures:")
        lines += [f"  {r['index']:>4}  {r.get('error') or '(no reason)'}" for r in failed]
    timed = sorted((r for r in runs if r.get("wall_s")), key=lambda r: -float(r["wall_s"]))
    if timed:
        lines.append("slowest:")
        lines += [f"  {r['index']:>4}  {r['wall_s']} s on {r.get('node')}"
                  for r in timed[:SLOWEST_SHOWN]]
    return "\n".join(lines)
