"""Flight reports: the thesis's hand-drawn Matlab analysis (section 6.1.3) as one command.

`companion logs report FLIGHT_DIR` writes PNG figures and one self-contained HTML page;
`companion logs view FLIGHT_DIR` replays the flight into rerun (companion.liveview).
User documentation: docs/report.md.

The names below are loaded on first use (PEP 562): importing this package, as the CLI does for
every `companion ...` command when it builds its parser, must not import matplotlib (about half
a second) for commands that draw nothing.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from companion.core.lazy import lazy_exports

if TYPE_CHECKING:
    from companion.report.autopilot_figures import AUTOPILOT_FIGURES
    from companion.report.figures import FIGURES, FigureSpec, MissingData
    from companion.report.flight import FlightData, LogStatus, load_flight
    from companion.report.report import BuiltFigure, ReportResult, build_figures, generate_report

__all__ = [
    "AUTOPILOT_FIGURES",
    "FIGURES",
    "BuiltFigure",
    "FigureSpec",
    "FlightData",
    "LogStatus",
    "MissingData",
    "ReportResult",
    "build_figures",
    "generate_report",
    "load_flight",
]

_HOME = {
    "AUTOPILOT_FIGURES": "autopilot_figures",
    "FIGURES": "figures",
    "FigureSpec": "figures",
    "MissingData": "figures",
    "FlightData": "flight",
    "LogStatus": "flight",
    "load_flight": "flight",
    "BuiltFigure": "report",
    "ReportResult": "report",
    "build_figures": "report",
    "generate_report": "report",
}


__getattr__, _dir = lazy_exports(__name__, {name: f"{__name__}.{module}"
                                           for name, module in _HOME.items()})


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
