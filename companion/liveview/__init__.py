"""Rerun views of a flight: live while it flies (`--rerun`), or replayed from its logs.

`LiveView` adds a low-priority managed thread that samples the vehicle's slots into rerun;
`replay_flight` sends a recorded flight directory, on its log timestamps. Both use the entity
paths in `companion.liveview.entities`. User documentation: docs/report.md.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from companion.core.config import Config
from companion.core.lazy import lazy_exports

# The rest is imported on first use (PEP 562): importing rerun opens sockets and takes time, and
# `companion logs ...` commands that draw nothing should pay for neither.
_LAZY = {
    "LiveView": "companion.liveview.thread",
    "LiveViewThread": "companion.liveview.thread",
    "Recording": "companion.liveview.sink",
    "ViewerError": "companion.liveview.sink",
    "open_recording": "companion.liveview.sink",
    "ReplayResult": "companion.liveview.replay",
    "replay_flight": "companion.liveview.replay",
    "replay_into": "companion.liveview.replay",
}

__all__ = ["live_view_bridges", *_LAZY]


__getattr__, __dir__ = lazy_exports(__name__, _LAZY)


def live_view_bridges(cfg: Config) -> list[Any]:
    """The runtime's `extra_bridges` for the configuration's `[rerun]` table (none when off)."""
    if not (cfg.rerun.enabled or cfg.rerun.save):
        return []
    from companion.liveview.thread import LiveView

    save = Path(cfg.rerun.save) if cfg.rerun.save else None
    return [lambda ctx, manager: LiveView(ctx, manager, spawn=cfg.rerun.enabled, save_path=save)]
