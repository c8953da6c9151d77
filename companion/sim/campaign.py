"""`companion sim --campaign SPEC --jobs J`: many simulated flights, one process each.

Researchers fly campaigns (seeds, wind, aircraft, sensor settings, parameter sets), and every
flight must be reproducible on its own: each one is a plain `companion sim` process with its own
flight directory and its own parameter file, so a flight of interest is re-flown by copying
its command line from `campaign.json`. Flights are lockstep by default (deterministic, as fast
as one core computes them); J flights run at a time.

The specification is TOML (or JSON with the same structure). Top-level keys are defaults for
every flight, `[grid]` gives lists whose Cartesian product is flown, and `[[flight]]` tables add
single flights:

    duration_s = 300
    scenario = "mixed"
    [grid]
    seed = [1, 2, 3]
    wind = [[0, 0, 0], [0, 8, 0]]
    [[flight]]
    seed = 100
    params = { CTL_ROLL_KP = 0.8 }

The campaign directory (a path or a URI) then holds `flights/NNNN` (one flight directory each),
`params/` (each flight's parameter file), `runs/NNNN.json` (each flight's completion marker),
`campaign.json` (every flight's settings, command, exit code, node, tries and figures) and
`dataset/`, the Parquet dataset of `companion logs export --dataset` that `companion logs query`
reads. Running the same command again flies only the flights without a marker (and, with
`retry_failed`, those whose marker says they failed).

The pieces: the specification (campaign_spec), the directory's state (campaign_state), where
flights fly (executors), what the user sees (progress), the parameter search (search).
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

from companion.core.files import dump_json
from companion.sim.campaign_spec import CampaignError, FlightSpec, load_campaign
from companion.sim.campaign_state import CampaignOutput
from companion.sim.executors import Events, FlightJob

log = logging.getLogger(__name__)

__all__ = ["CampaignError", "Executor", "FlightSpec", "load_campaign", "run_campaign"]


class Executor(Protocol):
    """What runs flights: `companion.sim.executors.LocalExecutor` or `RayExecutor`."""

    name: str
    slots: int

    def run(self, jobs: list[FlightJob], events: Events) -> dict[int, dict[str, Any]]: ...

    def close(self) -> None: ...


def plan(specs: list[FlightSpec], out: CampaignOutput, *, retry_failed: bool
         ) -> list[FlightSpec]:
    """The flights still to fly; the others get their recorded result back. Refuses (ValueError)
    a directory made for another campaign."""
    out.claim([s.settings for s in specs], "this specification")
    todo = []
    for spec in specs:
        marker = out.marker(spec.name)
        if marker is None or (retry_failed and marker.get("exit_code") != 0):
            todo.append(spec)
        else:
            spec.result = {k: v for k, v in marker.items() if k not in ("index", "settings")}
    return todo


def run_campaign(specs: list[FlightSpec], where: str, executor: Executor, *,
                 spec_path: Path | None = None, dataset: bool = True,
                 retry_failed: bool = False, events: Events | None = None
                 ) -> dict[str, Any]:
    """Fly every flight not yet flown, through `executor`; write campaign.json (and rebuild the
    dataset from every flight flown, now or before); return campaign.json's content.

    A KeyboardInterrupt stops the flights under way (none left running, none recorded) and is
    raised again once campaign.json says what was flown: the next run completes the rest."""
    out = CampaignOutput(where)
    todo = plan(specs, out, retry_failed=retry_failed)
    jobs = [FlightJob(s.index, s.name, s.settings, out.uri) for s in todo]
    by_index = {s.index: s for s in specs}
    t0 = time.monotonic()
    started = datetime.now(UTC).isoformat()
    interrupted = False

    def seen(kind: str, job: FlightJob, details: dict[str, Any]) -> None:
        if kind == "end":
            by_index[job.index].result = details
        if events is not None:
            events(kind, job, details)

    if events is not None:  # flown by an earlier run: counted, not flown again
        for spec in specs:
            if spec.result is not None:
                events("recorded", FlightJob(spec.index, spec.name, spec.settings, out.uri),
                       spec.result)
    try:
        executor.run(jobs, seen)
    except KeyboardInterrupt:
        interrupted = True
    wall_s = time.monotonic() - t0
    result = _result(specs, executor, started, wall_s, len(jobs), spec_path)
    result["interrupted"] = interrupted
    if dataset and not interrupted:
        result["dataset"] = _export(specs, out)
    out.write_text("campaign.json", dump_json(result) + "\n")
    if interrupted:
        raise KeyboardInterrupt
    return result


def _result(specs: list[FlightSpec], executor: Executor, started: str, wall_s: float,
            flown_now: int, spec_path: Path | None) -> dict[str, Any]:
    runs = [s.record() for s in specs]
    ok = [r for r in runs if r.get("exit_code") == 0]
    sim_s = sum(float(r.get("sim_s") or r["settings"]["duration_s"]) for r in ok)
    return {
        "specification": str(spec_path) if spec_path else None,
        "started_utc": started, "executor": executor.name, "slots": executor.slots,
        "flights": len(specs), "ok": len(ok), "failed": len(specs) - len(ok),
        "flown_now": flown_now, "wall_s": round(wall_s, 2), "simulated_s": round(sim_s, 2),
        "speed": round(sim_s / wall_s, 1) if wall_s > 0 else None,
        "restarts": sum(int(r.get("restarts") or 0) for r in runs),
        "runs": runs,
    }


def _export(specs: list[FlightSpec], out: CampaignOutput) -> dict[str, Any]:
    """The dataset rebuilt from every flight that flew: the same rows however many runs it took.
    Built on this machine's disk and then swapped (or copied) into place."""
    import pyarrow.fs as pafs

    from companion.logs.dataset import export_flight

    t0 = time.monotonic()
    exported, problems = 0, []
    fs, _ = out.fs_and_base
    local = out.local_dir
    work = Path(tempfile.mkdtemp(prefix=".dataset-", dir=local))
    try:
        built = work / "dataset"
        for spec in specs:
            if spec.result is None or spec.result.get("exit_code") != 0:
                continue
            flight = local / "flights" / spec.name if local else work / "flights" / spec.name
            if local is None:
                pafs.copy_files(out.path("flights", spec.name), str(flight),
                                source_filesystem=fs)
            try:
                done = export_flight(flight, built)
            except OSError as exc:
                problems.append(f"flight {spec.index}: {exc}")
                continue
            exported += 1
            problems += [f"flight {spec.index}: {p}" for p in done.problems]
        out.remove_dir("dataset")
        if built.exists():
            if local is not None:
                built.rename(local / "dataset")
            else:
                pafs.copy_files(str(built), out.path("dataset"), destination_filesystem=fs)
    except OSError as exc:
        problems.append(f"dataset: {exc.strerror or exc}")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return {"dir": out.path("dataset"), "flights": exported, "problems": problems,
            "export_s": round(time.monotonic() - t0, 2)}
