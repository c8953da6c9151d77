"""One self-contained HTML page: figures embedded as base64 PNG, no scripts, no network.

A report is read on a laptop in a field, often offline, and is mailed around as one file, so
everything it shows lives inside the page.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass
from html import escape

from companion.report.autopilot import AutopilotSummary
from companion.report.summary import Summary

__all__ = ["FigureEntry", "render_html"]

_CSS = """
body{font-family:system-ui,sans-serif;margin:1.5em auto;max-width:1000px;color:#222}
h1{font-size:1.4em}h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;font-size:.85em;margin:.5em 0}
td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}
th{background:#f0f0f0}td:first-child,th:first-child{text-align:left}
.bad{color:#b00}.note{color:#555;font-size:.85em}img{max-width:100%}
"""


@dataclass(frozen=True)
class FigureEntry:
    name: str
    title: str
    thesis: str
    png: bytes | None
    missing: str | None


def _size(n: int | None) -> str:
    if n is None:
        return "-"
    if n >= 1_000_000:
        return f"{n / 1e6:.2f} MB"
    if n >= 1000:
        return f"{n / 1e3:.1f} kB"
    return f"{n} B"


def _num(v: object, fmt: str = "{}") -> str:
    return "-" if v is None else escape(fmt.format(v))


def _summary_table(s: Summary) -> str:
    ratio = (f"{s.csv_bytes / s.binary_bytes:.1f}x" if s.csv_bytes and s.binary_bytes else "-")
    rows = [
        ("flight directory", s.flight_dir),
        ("started (UTC, from run.json)", s.started_utc),
        ("software", s.software),
        ("kind", s.simulation),
        ("duration", f"{s.duration_s:.1f} s" + (f" (clock scale {s.clock_scale:g})" if s.clock_scale else "")),
        ("threads", f"{len(s.threads)}: " + ", ".join(t.name for t in s.threads)),
        ("restarts", str(s.restarts)),
        ("log size (binary)", _size(s.binary_bytes)),
        ("same logs as CSV", f"{'~' if s.csv_estimated else ''}{_size(s.csv_bytes)} ({ratio} the binary size"
                             + ("; long formats sampled" if s.csv_estimated else "") + ")"),
    ]
    rows += [(k, str(v)) for k, v in s.counters.items()]
    if s.autopilot is not None:
        rows += _autopilot_rows(s.autopilot)
    body = "".join(f"<tr><th>{escape(k)}</th><td>{escape(v)}</td></tr>" for k, v in rows)
    return f"<table>{body}</table>"


def _angles(deg: tuple[float, float, float]) -> str:
    return f"roll {deg[0]:.2f}, pitch {deg[1]:.2f}, yaw {deg[2]:.2f} deg"


def _autopilot_rows(a: AutopilotSummary) -> list[tuple[str, str]]:
    """Rows of a flight beside a flight controller (autopilot.bin)."""
    att, sync, sent = a.attitude, a.sync, a.targets
    rows = [("attitude, ours - autopilot (RMS)",
             f"{_angles(att.rms_diff_deg)} ({att.n} samples, {att.span_s:.1f} s)" if att is not None
             else f"not compared: {a.attitude_missing}")]
    if att is not None:
        rows += [(f"attitude RMSE against truth, {who}", _angles(rmse))
                 for who, rmse in (("ours", att.ours_rmse_deg), ("autopilot", att.autopilot_rmse_deg))
                 if rmse is not None]
    rows.append(("autopilot clock map",
                 f"{sync.n} round trips, drift {sync.drift_ppm[-1]:.2f} ppm (last), latency "
                 f"{sync.latency_median_ms:.2f} ms (median), {sync.reset_count} "
                 f"restart{'' if sync.reset_count == 1 else 's'}" if sync is not None
                 else f"not logged: {a.sync_missing}"))
    if sent is not None:
        rows.append(("attitude targets sent in GUIDED", f"{sent.n} over {sent.span_s:.1f} s"))
    return rows


def _logs_table(s: Summary) -> str:
    head = ("<tr><th>log</th><th>size</th><th>CSV</th><th>records</th><th>formats</th>"
            "<th>Begin Data</th><th>closed</th><th>span (s)</th><th>problems</th></tr>")
    out = []
    for r in s.logs:
        if not r.present:
            out.append(f"<tr><td>{escape(r.name)}.bin</td><td colspan=8 class=bad>missing</td></tr>")
            continue
        problems = "<br>".join(escape(p) for p in r.problems) or "none"
        out.append(
            f"<tr><td>{escape(r.name)}.bin</td><td>{_size(r.size_bytes)}</td><td>{_size(r.csv_bytes)}</td>"
            f"<td>{r.records}</td><td>{r.formats}</td><td>{r.begins}</td>"
            f"<td>{'yes' if r.closed_cleanly else '<span class=bad>no</span>'}</td>"
            f"<td>{_num(r.span_s, '{:.1f}')}</td>"
            f"<td{' class=bad' if r.problems else ''} style='text-align:left'>{problems}</td></tr>")
    return f"<table>{head}{''.join(out)}</table>"


def _threads_table(s: Summary) -> str:
    head = ("<tr><th>thread</th><th>restarts</th><th>source</th><th>cycles</th><th>rate (Hz)</th>"
            "<th>stalls</th><th>mean step (us)</th><th>worst step (us)</th><th>missed deadlines</th>"
            "<th>log records dropped</th></tr>")
    out = [
        f"<tr><td>{escape(t.name)}</td><td>{_num(t.restarts)}</td><td>{escape(t.source)}</td>"
        f"<td>{_num(t.cycles)}</td><td>{_num(t.rate_hz)}</td><td>{_num(t.stalls)}</td>"
        f"<td>{_num(t.mean_step_us)}</td><td>{_num(t.worst_step_us)}</td>"
        f"<td>{_num(t.missed_deadlines)}</td><td>{_num(t.log_dropped)}</td></tr>"
        for t in s.threads
    ]
    note = ("" if any(t.source == "summary.json" for t in s.threads) else
            "<p class=note>Step times, stalls, watchdog events and dropped log records are not in "
            "the logs; this flight directory has no summary.json, so restarts are counted from "
            "Begin Data records.</p>")
    return f"<table>{head}{''.join(out)}</table>{note}"


def _events_section(s: Summary) -> str:
    """Every fault a simulation injected, and what the runtime reported: the two side by side
    are how a fault campaign's flight is read."""
    if not s.event_counts and not s.injected:
        return "<p class=note>No event reported (no summary.json, or nothing happened).</p>"
    parts = []
    if s.injected:
        parts.append("<p>Injected on purpose:</p><ul>")
        parts += [f"<li>{escape(i)}</li>" for i in s.injected]
        parts.append("</ul>")
    if s.event_counts:
        parts.append("<table><tr><th>thread</th><th>event</th><th>count</th></tr>")
        parts += [f"<tr><td>{escape(t)}</td><td>{escape(k)}</td><td>{n}</td></tr>"
                  for (t, k), n in sorted(s.event_counts.items())]
        parts.append("</table><table><tr><th>flight time (s)</th><th>thread</th><th>event</th>"
                     "<th>detail</th></tr>")
        parts += [f"<tr><td>{e.t_s:.2f}</td><td>{escape(e.thread)}</td><td>{escape(e.kind)}"
                  f"</td><td>{escape(e.detail)}</td></tr>" for e in s.events]
        parts.append("</table>")
        listed, total = len(s.events), sum(s.event_counts.values())
        if total > listed:
            parts.append(f"<p class=note>The first {listed} of {total} events are listed.</p>")
    return "".join(parts)


def render_html(summary: Summary, figures: list[FigureEntry], problems: list[str]) -> str:
    """The report page; deterministic for a given input (no generation time)."""
    parts = [
        "<!DOCTYPE html><html lang=en><head><meta charset=utf-8>",
        f"<title>Flight report {escape(summary.flight_dir)}</title><style>{_CSS}</style></head><body>",
        f"<h1>Flight report: {escape(summary.flight_dir)}</h1>",
        "<h2>Summary</h2>", _summary_table(summary),
        "<h2>Logs</h2>", _logs_table(summary),
        "<h2>Threads</h2>", _threads_table(summary),
        "<h2>Faults and events</h2>", _events_section(summary),
    ]
    missing = [f for f in figures if f.png is None]
    if problems or missing:
        parts.append("<h2>Missing or damaged</h2><ul>")
        parts += [f"<li class=bad>{escape(p)}</li>" for p in problems]
        parts += [f"<li>{escape(f.title)}: {escape(f.missing or 'not drawn')}</li>" for f in missing]
        parts.append("</ul>")
    for f in figures:
        if f.png is None:
            continue
        data = base64.b64encode(f.png).decode("ascii")
        parts.append(f"<h2 id={escape(f.name)}>{escape(f.title)} <span class=note>"
                     f"({escape(f.thesis)})</span></h2>")
        parts.append(f"<img alt='{escape(f.title)}' src='data:image/png;base64,{data}'>")
    parts.append("</body></html>\n")
    return "\n".join(parts)
