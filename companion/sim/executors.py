"""Where a campaign's flights fly: in local processes (a pool of `--jobs` threads, each running
one `companion sim` process) or as Ray tasks on a cluster (`--executor ray`).

Both run the same function, `fly`, for one flight: it runs the flight's own command line (kept
in its record so the flight is re-flown alone by hand), puts the flight directory at the
campaign's output under the flight's name, and writes the completion marker last. What differs
is only who calls it: a thread here, or a Ray task on any node (one CPU each); a task lost with
its node is sent again, up to `max_tries`, and then recorded failed with the reason.

A flight process dies with the process that started it (PR_SET_PDEATHSIG): a Ray worker killed
with its node, or a pool killed with its driver, leaves no orphan flight behind.
"""

from __future__ import annotations

import ctypes
import json
import logging
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.sim.campaign_spec import FLIGHT_MARGIN_S, flight_command
from companion.sim.campaign_state import CampaignOutput

log = logging.getLogger(__name__)

__all__ = ["FlightJob", "LocalExecutor", "RayExecutor", "ExecutorError", "fly"]

PR_SET_PDEATHSIG = 1
RAY_INIT_TIMEOUT_S = 30.0
"""Longest wait for a cluster to answer: an unreachable address is an error, never a hang."""


class ExecutorError(RuntimeError):
    """The executor cannot start (Ray missing, cluster unreachable): one line, nothing flown."""


@dataclass(frozen=True)
class FlightJob:
    """One flight to fly: everything a worker on any node needs, and nothing of the driver."""

    index: int
    name: str
    settings: dict[str, Any]
    out_uri: str
    attempt: int = 1

    @property
    def timeout_s(self) -> float:
        return float(self.settings["duration_s"]) + FLIGHT_MARGIN_S


Events = Callable[[str, FlightJob, dict[str, Any]], None]
"""(event, job, details): "start" (details: node), "retry" (reason), "end" (the record);
and from run_campaign, "recorded" (the record of a flight an earlier run flew)."""


def _die_with_parent() -> None:
    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


def fly(job: FlightJob, node: str, on_spawn: Callable[[subprocess.Popen[str]], None] | None = None,
        stopping: Callable[[], bool] = lambda: False) -> dict[str, Any] | None:
    """Fly `job` on this machine and leave it at the campaign output; its record, which is also
    its completion marker (None when the campaign was stopped under it: nothing is recorded and
    the next run flies it again)."""
    from companion.sim.flight_metrics import flight_metrics

    out = CampaignOutput(job.out_uri)
    local = out.local_dir
    params = job.settings.get("params") or {}
    params_text = "".join(f"{name} {value}\n" for name, value in params.items())
    scratch = Path(tempfile.mkdtemp(prefix=f"campaign-{job.name}-"))
    log_dir = scratch / "flights"
    try:
        if local is not None:  # the command names the campaign's own files: re-flown by hand
            params_file = local / "params" / f"{job.name}.parm"
            log_dir = local / "flights" / f".{job.name}.partial"
            shutil.rmtree(log_dir, ignore_errors=True)
        else:
            params_file = scratch / f"{job.name}.parm"
        out.write_text(f"params/{job.name}.parm", params_text)
        if local is None:
            params_file.write_text(params_text, encoding="utf-8")
        command = flight_command(job.settings, str(log_dir), str(params_file))
        record: dict[str, Any] = {"command": command, "node": node, "tries": job.attempt,
                                  "error": "", "restarts": 0}
        t0 = time.monotonic()
        proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True, preexec_fn=_die_with_parent)
        if on_spawn is not None:
            on_spawn(proc)
        try:
            stdout, stderr = proc.communicate(timeout=job.timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            stdout, stderr = proc.communicate()
            record["error"] = f"no result within {job.timeout_s:.0f} s: killed"
        if stopping():
            return None
        record["wall_s"] = round(time.monotonic() - t0, 2)
        record["exit_code"] = proc.returncode
        try:
            summary = json.loads(stdout) if stdout.strip() else {}
        except json.JSONDecodeError:
            summary = {}
        if proc.returncode != 0 and not record["error"]:
            record["error"] = (stderr.strip().splitlines() or ["(no message)"])[-1][:300]
        record.update(_figures(summary))
        flown = summary.get("flight_dir")
        if flown and Path(flown).is_dir():
            record["metrics"] = flight_metrics(Path(flown), summary)
            record["flight_dir"] = _place(out, Path(flown), job.name)
        else:
            record["flight_dir"] = None
        out.write_marker(job.name, record)
        return record
    except OSError as exc:  # the output cannot be written (a full disk, no permission)
        return {"command": [], "node": node, "tries": job.attempt, "exit_code": None,
                "restarts": 0, "wall_s": None, "flight_dir": None,
                "error": f"output {job.out_uri}: {exc.strerror or exc}"}
    finally:  # what is left of a flight not placed (a full disk) is not kept
        shutil.rmtree(log_dir, ignore_errors=True)
        shutil.rmtree(scratch, ignore_errors=True)


def _place(out: CampaignOutput, flown: Path, name: str) -> str:
    """Move (on the same disk) or copy (to a bucket) the flight directory to flights/NAME."""
    import pyarrow.fs as pafs

    out.remove_dir(f"flights/{name}")
    target = out.path("flights", name)
    fs, _ = out.fs_and_base
    if out.local_dir is not None:
        fs.move(str(flown), target)
    else:
        pafs.copy_files(str(flown), target, destination_filesystem=fs)
    return target if out.local_dir is not None else f"{out.uri.rstrip('/')}/flights/{name}"


def _figures(summary: dict[str, Any]) -> dict[str, Any]:
    threads = summary.get("threads") or []
    return {
        "stop_reason": summary.get("stop_reason"),
        "restarts": sum(int(t.get("restarts") or 0) for t in threads),
        "failed_threads": [t.get("name") for t in threads if t.get("failed")],
        "speed": (summary.get("lockstep") or {}).get("speed"),
        "sim_s": (summary.get("lockstep") or {}).get("sim_seconds"),
    }


class LocalExecutor:
    """`--jobs` flights at a time, each a process of this machine (the default)."""

    name = "local"

    def __init__(self, jobs: int) -> None:
        self.slots = jobs
        self._host = socket.gethostname()

    def run(self, jobs: list[FlightJob], events: Events) -> dict[int, dict[str, Any]]:
        from concurrent.futures import ThreadPoolExecutor

        stop = threading.Event()
        running: set[subprocess.Popen[str]] = set()
        lock = threading.Lock()
        results: dict[int, dict[str, Any]] = {}

        def spawned(proc: subprocess.Popen[str]) -> None:
            with lock:
                running.add(proc)

        def one(job: FlightJob) -> None:
            if stop.is_set():
                return
            events("start", job, {"node": self._host})
            record = fly(job, self._host, spawned, stop.is_set)
            if record is not None:
                results[job.index] = record
                events("end", job, record)

        pool = ThreadPoolExecutor(max_workers=self.slots, thread_name_prefix="campaign")
        futures = [pool.submit(one, j) for j in jobs]
        try:
            for f in futures:
                f.result()
        except KeyboardInterrupt:
            stop.set()
            with lock:
                for proc in running:
                    proc.send_signal(signal.SIGINT)
            for f in futures:
                f.result()
            raise
        finally:
            pool.shutdown(wait=True)
        return results

    def close(self) -> None:
        pass


def _ray_task(job: FlightJob, queue: Any) -> dict[str, Any] | None:
    """A Ray task: tell the driver where it flies, then fly."""
    import ray

    node = ray.get_runtime_context().get_node_id()
    try:
        queue.put_nowait((job.index, job.attempt, node))
    except Exception:  # noqa: BLE001 - the progress line is not worth losing the flight for
        log.debug("progress queue unreachable")
    return fly(job, node)


class RayExecutor:
    """Each flight one Ray task of one CPU, on the cluster at `address` (or a local one that
    ray.init starts when there is no address)."""

    name = "ray"

    def __init__(self, address: str | None, jobs: int | None, max_tries: int = 3) -> None:
        try:
            import ray
        except ImportError:
            raise ExecutorError("--executor ray needs Ray: pip install 'uav-companion[cluster]'"
                                ) from None
        self._ray = ray
        self.max_tries = max_tries
        if address and address != "auto":
            _reachable(address)
        # Ray's driver prints what its cluster says (a raylet that died, ...) on stdout, from
        # its own threads, at any time until shutdown; `--json` puts the campaign's result on
        # stdout: Ray's lines go to stderr while the executor lives
        self._stdout = sys.stdout
        sys.stdout = sys.stderr
        try:
            self._release = _bounded_init(ray, address)
        except BaseException:
            sys.stdout = self._stdout
            raise
        cpus = int(ray.cluster_resources().get("CPU", 1))
        self.slots = jobs if jobs else max(1, cpus)
        from ray.util.queue import Queue
        from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

        here = ray.get_runtime_context().get_node_id()
        # the progress queue lives on the driver's node: it must outlive any worker node
        self._queue = Queue(actor_options={"num_cpus": 0, "scheduling_strategy":
                                           NodeAffinitySchedulingStrategy(here, soft=False)})
        self._remote = ray.remote(num_cpus=1, max_retries=0)(_ray_task)

    def run(self, jobs: list[FlightJob], events: Events) -> dict[int, dict[str, Any]]:
        ray = self._ray
        from collections import deque

        pending = deque(jobs)
        inflight: dict[Any, FlightJob] = {}
        results: dict[int, dict[str, Any]] = {}
        try:
            while pending or inflight:
                while pending and len(inflight) < self.slots:
                    job = pending.popleft()
                    inflight[self._remote.remote(job, self._queue)] = job
                ready, _ = ray.wait(list(inflight), num_returns=1, timeout=0.5)
                self._drain(inflight, events)
                for ref in ready:
                    job = inflight.pop(ref)
                    try:
                        record = ray.get(ref)
                    except ray.exceptions.RayTaskError as exc:  # a bug in fly: no retry
                        record = _lost(job, f"task raised {exc.cause!r}"[:300])
                    except ray.exceptions.RayError as exc:  # its worker or node was lost
                        reason = f"{type(exc).__name__} on try {job.attempt}"
                        if job.attempt < self.max_tries:
                            events("retry", job, {"reason": reason})
                            pending.appendleft(_again(job))
                            continue
                        record = _lost(job, f"lost {job.attempt} times (last: {reason})")
                        CampaignOutput(job.out_uri).write_marker(job.name, record)
                    if record is not None:
                        results[job.index] = record
                        events("end", job, record)
        except KeyboardInterrupt:
            for ref in inflight:
                ray.cancel(ref, force=True)  # the worker dies, its flight with it
            raise
        return results

    def _drain(self, inflight: dict[Any, FlightJob], events: Events) -> None:
        by_index = {j.index: j for j in inflight.values()}
        while True:
            try:
                index, attempt, node = self._queue.get_nowait()
            except Exception:  # noqa: BLE001 - queue.Empty, or the queue is gone
                return
            job = by_index.get(index)
            if job is not None and job.attempt == attempt:
                events("start", job, {"node": node})

    def close(self) -> None:
        try:
            self._ray.shutdown()
        except Exception:  # noqa: BLE001 - shutting down a cluster link that already broke
            log.debug("ray.shutdown failed", exc_info=True)
        self._release.set()
        sys.stdout = self._stdout


def _again(job: FlightJob) -> FlightJob:
    return FlightJob(job.index, job.name, job.settings, job.out_uri, job.attempt + 1)


def _lost(job: FlightJob, reason: str) -> dict[str, Any]:
    return {"command": [], "node": None, "tries": job.attempt, "exit_code": None,
            "restarts": 0, "wall_s": None, "flight_dir": None, "error": reason}


def _reachable(address: str) -> None:
    """A clear error for a cluster that does not answer, before Ray's own long retries."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise ExecutorError(f"--ray-address {address!r}: expected HOST:PORT (the head's GCS "
                            "port, 6379 by default) or 'auto'")
    try:
        socket.create_connection((host, int(port)), timeout=5.0).close()
    except OSError as exc:
        raise ExecutorError(f"--ray-address {address}: no Ray cluster answers there "
                            f"({exc.strerror or exc})") from None


def _bounded_init(ray: Any, address: str | None) -> threading.Event:
    """ray.init in a thread, given up after RAY_INIT_TIMEOUT_S: never a hang. The thread stays
    until the returned event is set: Ray ties the local cluster's processes to the life of the
    thread that started them (PR_SET_PDEATHSIG), so it must outlive the campaign."""
    failure: list[BaseException] = []
    ready, release = threading.Event(), threading.Event()

    def init() -> None:
        try:
            # a local cluster stays on loopback: nothing of it reachable from the network;
            # and a cluster on loopback is found by this driver on loopback too
            extra: dict[str, Any] = {} if address else {"include_dashboard": False}
            if not address or address.rpartition(":")[0] in ("127.0.0.1", "localhost"):
                extra["_node_ip_address"] = "127.0.0.1"
            ray.init(address=address or None, logging_level=logging.WARNING,
                     log_to_driver=False, **extra)
        except BaseException as exc:  # noqa: BLE001 - reported on the caller's thread
            failure.append(exc)
        ready.set()
        release.wait()

    threading.Thread(target=init, name="ray-init", daemon=True).start()
    if not ready.wait(RAY_INIT_TIMEOUT_S):
        raise ExecutorError(f"Ray did not start or connect within {RAY_INIT_TIMEOUT_S:.0f} s "
                            f"(address {address or 'local'})")
    if failure:
        release.set()
        first = str(failure[0]).strip().splitlines() or [type(failure[0]).__name__]
        raise ExecutorError(f"Ray could not start or connect (address {address or 'local'}): "
                            f"{first[0][:200]}")
    return release
