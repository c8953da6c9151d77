"""Flight reports: the thesis's hand-drawn Matlab analysis (section 6.1.3) as one command.

`companion logs report FLIGHT_DIR` writes PNG figures and one self-contained HTML page;
`companion logs view FLIGHT_DIR` replays the flight into rerun (companion.liveview).
User documentation: docs/report.md.
"""

from __future__ import annotations

from companion.report.figures import FIGURES, FigureSpec, MissingData
from companion.report.flight import FlightData, LogStatus, load_flight
from companion.report.report import BuiltFigure, ReportResult, build_figures, generate_report

__all__ = [
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
