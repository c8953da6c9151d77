"""`companion sim --campaign SPEC --search`: an Optuna study of a campaign's parameters.

The specification's top-level keys are the flight every trial flies; its `[search]` table names
the parameters with their ranges, the metric to minimise (or maximise) and the trial budget:

    duration_s = 10
    scenario = "level"
    [search]
    metric = "roll_rmse_deg"     # companion.sim.flight_metrics, or a summary.json path
    trials = 12
    seed = 1                     # the sampler's: the same study twice
    [search.params]
    EST_TRIM_ROLL = [-0.1, 0.1]  # [low, high]; an int32 parameter draws integers

Trials fly through the campaign's executor (local processes or Ray), a batch of as many as it
flies at a time (Optuna's ask and tell), each a flight of the campaign directory like any other
(`flights/tNNNN`, its command in its marker). The study lives in a database (SQLite in the
campaign directory unless --search-storage names one), so the same command resumes it. At the
end `best.parm` holds the best parameters (NAME VALUE lines, which --params-file and MAVProxy's
`param load` read) and `dataset/search/trials.parquet` the study's history.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.sim.campaign_spec import CampaignError, base_settings, check_params, read_spec
from companion.sim.campaign_state import CampaignOutput
from companion.sim.executors import Events, FlightJob
from companion.sim.flight_metrics import check_metric, metric_value

log = logging.getLogger(__name__)

__all__ = ["SearchSpec", "load_search", "run_search"]

SEARCH_KEYS = {"metric", "direction", "trials", "seed", "params", "storage"}
STUDY_NAME = "campaign-search"


@dataclass(frozen=True)
class SearchSpec:
    """A checked [search] table and the flight each trial flies."""

    path: Path
    base: dict[str, Any]
    ranges: dict[str, tuple[float, float, bool]]  # name: (low, high, integer)
    metric: str
    direction: str
    trials: int
    seed: int | None
    storage: str | None


def load_search(path: Path) -> SearchSpec:
    """The search a specification describes, every error (unknown parameter, empty range, a
    metric no flight gives) found before anything flies."""
    spec = read_spec(path)
    table = spec.get("search")
    where = f"{path}: [search]"
    if not isinstance(table, dict):
        raise CampaignError(f"{path}: --search needs a [search] table (metric, trials, params)")
    unknown = set(table) - SEARCH_KEYS
    if unknown:
        raise CampaignError(f"{where}: unknown key {sorted(unknown)[0]!r} "
                            f"(known: {', '.join(sorted(SEARCH_KEYS))})")
    metric = table.get("metric")
    if not isinstance(metric, str):
        raise CampaignError(f"{where}: metric: expected the name of a flight metric")
    problem = check_metric(metric)
    if problem:
        raise CampaignError(f"{where}: {problem}")
    direction = table.get("direction", "minimize")
    if direction not in ("minimize", "maximize"):
        raise CampaignError(f"{where}: direction = {direction!r}: minimize or maximize")
    trials = table.get("trials")
    if not isinstance(trials, int) or isinstance(trials, bool) or trials < 1:
        raise CampaignError(f"{where}: trials = {trials!r}: expected a whole number >= 1")
    seed = table.get("seed")
    if seed is not None and (not isinstance(seed, int) or isinstance(seed, bool)):
        raise CampaignError(f"{where}: seed = {seed!r}: expected an int")
    storage = table.get("storage")
    if storage is not None and not isinstance(storage, str):
        raise CampaignError(f"{where}: storage: expected a database URL")
    base = base_settings(spec, path)
    ranges = _ranges(table.get("params"), f"{where}.params")
    # both ends of every range must be values the runtime accepts
    for end in (0, 1):
        params = {**(base.get("params") or {}), **{n: r[end] for n, r in ranges.items()}}
        check_params([{**base, "params": params}], path)
    return SearchSpec(path, base, ranges, metric, direction, trials, seed, storage)


def _ranges(table: Any, where: str) -> dict[str, tuple[float, float, bool]]:
    from companion.core.config import Config
    from companion.core.params import ParamType
    from companion.runtime import declared_registry

    if not isinstance(table, dict) or not table:
        raise CampaignError(f"{where}: expected a table NAME = [low, high], at least one")
    registry = declared_registry(Config())
    ranges = {}
    for name, bounds in table.items():
        if name not in registry:
            raise CampaignError(f"{where}: {name}: unknown parameter")
        if (not isinstance(bounds, list) or len(bounds) != 2 or not all(
                isinstance(b, int | float) and not isinstance(b, bool) for b in bounds)):
            raise CampaignError(f"{where}: {name} = {bounds!r}: expected [low, high]")
        low, high = float(bounds[0]), float(bounds[1])
        if not low < high:
            raise CampaignError(f"{where}: {name} = {bounds!r}: empty range (low must be "
                                "below high)")
        ranges[name] = (low, high, registry.spec(name).ptype is ParamType.INT32)
    return ranges


def run_search(search: SearchSpec, where: str, executor: Any, *, storage: str | None = None,
               events: Events | None = None) -> dict[str, Any]:
    """Run (or resume) the study to its trial budget; write best.parm and the history table;
    return a summary of the study."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    out = CampaignOutput(where)
    out.claim([{"search": search.path.name, **search.base}], "this search")
    url = storage or search.storage or _default_storage(out)
    study = optuna.create_study(study_name=STUDY_NAME, storage=url, load_if_exists=True,
                                direction=(optuna.study.StudyDirection.MAXIMIZE
                                           if search.direction == "maximize"
                                           else optuna.study.StudyDirection.MINIMIZE),
                                sampler=optuna.samplers.TPESampler(
                                    seed=search.seed, n_startup_trials=_startup(search.trials)))
    finished = (optuna.trial.TrialState.COMPLETE, optuna.trial.TrialState.FAIL)
    while True:
        done = sum(1 for t in study.trials if t.state in finished)
        if done >= search.trials:
            break
        batch = [study.ask() for _ in range(min(executor.slots, search.trials - done))]
        jobs = [_job(search, trial, out) for trial in batch]
        records = executor.run(jobs, events or (lambda *_: None))
        for trial, job in zip(batch, jobs, strict=True):
            record = records.get(job.index)
            value = None if record is None else metric_value(record, search.metric)
            if value is None:
                why = ("not flown" if record is None else record.get("error")
                       or f"no {search.metric} in the flight's metrics")
                trial.set_user_attr("failure", why)
                study.tell(trial, state=optuna.trial.TrialState.FAIL)
            else:
                trial.set_user_attr("flight", job.name)
                study.tell(trial, value)
    return _conclude(study, search, out, url)


def _startup(trials: int) -> int:
    """Random trials before the sampler models the metric: Optuna's 10 would spend a small
    budget (a dozen short flights) on chance alone; a third of it, at least 2, at most 10."""
    return max(2, min(10, trials // 3))


def _default_storage(out: CampaignOutput) -> str:
    if out.local_dir is None:
        raise CampaignError(f"{out.uri}: a search's study needs a database: SQLite cannot live "
                            "in a bucket; give --search-storage URL (e.g. postgresql://...)")
    out.local_dir.mkdir(parents=True, exist_ok=True)
    return f"sqlite:///{out.local_dir / 'study.db'}"


def _job(search: SearchSpec, trial: Any, out: CampaignOutput) -> FlightJob:
    params = dict(search.base.get("params") or {})
    for name, (low, high, integer) in search.ranges.items():
        params[name] = (trial.suggest_int(name, int(math.ceil(low)), int(math.floor(high)))
                        if integer else trial.suggest_float(name, low, high))
    settings = {**search.base, "params": params}
    # trial numbers start at 0; a flight's index at 1
    return FlightJob(trial.number + 1, f"t{trial.number:04d}", settings, out.uri)


def _conclude(study: Any, search: SearchSpec, out: CampaignOutput, url: str) -> dict[str, Any]:
    import io

    import pyarrow as pa
    import pyarrow.parquet as pq

    from companion.core.config import Config
    from companion.core.params import format_value
    from companion.runtime import declared_registry

    complete = [t for t in study.trials if t.value is not None]
    if not complete:
        raise CampaignError(f"{search.path}: no trial gave {search.metric}: "
                            + "; ".join(str(t.user_attrs.get("failure")) for t in study.trials[:3]))
    registry = declared_registry(Config())
    best = study.best_trial
    lines = [f"# best of {len(study.trials)} trials of {search.path.name}: "
             f"{search.metric} = {best.value:.6g} (flight {best.user_attrs.get('flight')})"]
    lines += [f"{n:<16} {format_value(registry.spec(n).ptype, v)}"
              for n, v in best.params.items()]
    out.write_text("best.parm", "\n".join(lines) + "\n")
    history = study.trials_dataframe(attrs=("number", "value", "state", "params",
                                            "user_attrs", "duration"))
    history["state"] = history["state"].astype(str)
    if "duration" in history:
        history["duration_s"] = history.pop("duration").dt.total_seconds()
    sink = io.BytesIO()
    pq.write_table(pa.Table.from_pandas(history, preserve_index=False), sink)
    fs, _ = out.fs_and_base
    fs.create_dir(out.path("dataset", "search"), recursive=True)
    with fs.open_output_stream(out.path("dataset", "search", "trials.parquet")) as dst:
        dst.write(sink.getvalue())
    return {"metric": search.metric, "direction": search.direction,
            "trials": len(study.trials), "failed": len(study.trials) - len(complete),
            "best_value": best.value, "best_params": best.params,
            "best_flight": best.user_attrs.get("flight"), "storage": url,
            "best_parm": out.path("best.parm"),
            "history": out.path("dataset", "search", "trials.parquet")}
