"""On-board runtime for fixed-wing UAV research: supervised threads, logs, drivers, SITL."""

from __future__ import annotations

__version__ = "0.1.0"
