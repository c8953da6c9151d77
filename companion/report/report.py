"""`generate_report`: a flight directory in, PNG figures and one HTML page out."""

from __future__ import annotations

import io
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import matplotlib
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from companion.report.autopilot_figures import figures_for
from companion.report.figures import STYLE, MissingData, Products
from companion.report.flight import FlightData, load_flight
from companion.report.html import FigureEntry, render_html
from companion.report.summary import Summary, summarise

__all__ = ["BuiltFigure", "ReportResult", "build_figures", "generate_report"]

log = logging.getLogger(__name__)

_RC: Any = STYLE  # matplotlib types its keys as a Literal union


@dataclass
class BuiltFigure:
    name: str
    title: str
    thesis: str
    figure: Figure | None
    missing: str | None


@dataclass
class ReportResult:
    """What a report wrote, and what it could not draw and why."""

    figures: list[Path]
    html: Path
    missing: list[str]  # "<figure title>: <reason>" for every figure not drawn
    problems: list[str]  # damaged, truncated, unreadable or absent inputs
    summary: Summary
    figure_objects: dict[str, Figure] = field(default_factory=dict)


def build_figures(fd: FlightData) -> list[BuiltFigure]:
    """Every report figure for `fd`, drawn or with the reason it could not be."""
    products = Products(fd)
    out = []
    with matplotlib.rc_context(_RC):
        for spec in figures_for(fd):
            try:
                fig: Figure | None = spec.build(products)
                reason = None
            except MissingData as exc:
                fig, reason = None, str(exc)
            except Exception as exc:  # one bad figure must not cost the whole report
                log.warning("figure %s failed: %s", spec.name, exc, exc_info=log.isEnabledFor(logging.DEBUG))
                fig, reason = None, f"could not be drawn: {type(exc).__name__}: {exc}"
            out.append(BuiltFigure(spec.name, spec.title, spec.thesis, fig, reason))
    return out


def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    with matplotlib.rc_context(_RC):
        # print_png draws once (savefig twice); no "Software" or date chunk: same flight, same bytes.
        FigureCanvasAgg(fig).print_png(buf, metadata={"Software": None})
    return buf.getvalue()


def generate_report(flight_dir: str | Path, out_dir: str | Path | None = None, *,
                    measure_csv: bool = True, keep_figures: bool = False) -> ReportResult:
    """Write ``<name>.png`` per figure and ``report.html`` into `out_dir` (default
    ``FLIGHT_DIR/report``).

    Raises FileNotFoundError when `flight_dir` is not a directory and OSError when the output
    cannot be written; a damaged or partial flight still gives a report that lists what is
    missing. `measure_csv` converts each log to CSV in a scratch directory to report the size.
    """
    fd = load_flight(flight_dir)
    out = Path(out_dir) if out_dir is not None else fd.flight_dir / "report"
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise(fd, measure_csv=measure_csv)
    built = build_figures(fd)
    paths: list[Path] = []
    entries: list[FigureEntry] = []
    for b in built:
        png = None
        if b.figure is not None:
            png = _png(b.figure)
            path = out / f"{b.name}.png"
            path.write_bytes(png)
            paths.append(path)
        else:
            stale = out / f"{b.name}.png"
            if stale.exists():  # from an earlier report of a fuller flight: not this one's
                stale.unlink()
        entries.append(FigureEntry(b.name, b.title, b.thesis, png, b.missing))
    html_path = out / "report.html"
    html_path.write_text(render_html(summary, entries, fd.problems), encoding="utf-8")
    return ReportResult(
        figures=paths,
        html=html_path,
        missing=[f"{b.title}: {b.missing}" for b in built if b.figure is None],
        problems=list(fd.problems),
        summary=summary,
        figure_objects={b.name: b.figure for b in built if b.figure is not None} if keep_figures else {},
    )
