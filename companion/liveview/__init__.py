"""Rerun views of a flight: live while it flies (`--rerun`), or replayed from its logs.

`LiveView` adds a low-priority managed thread that samples the vehicle's slots into rerun;
`replay_flight` sends a recorded flight directory, on its log timestamps. Both use the entity
paths in `companion.liveview.entities`. User documentation: docs/report.md.
"""

from __future__ import annotations

from typing import Any

from companion.core.config import Config
from companion.liveview.replay import ReplayResult, replay_flight, replay_into
from companion.liveview.sink import Recording, ViewerError, open_recording
from companion.liveview.thread import LiveView, LiveViewThread

__all__ = [
    "LiveView",
    "live_view_bridges",
    "LiveViewThread",
    "Recording",
    "ReplayResult",
    "ViewerError",
    "open_recording",
    "replay_flight",
    "replay_into",
]


def live_view_bridges(cfg: Config) -> list[Any]:
    """The runtime's `extra_bridges` for the configuration's `[rerun]` table (none when off)."""
    if not (cfg.rerun.enabled or cfg.rerun.save):
        return []
    from pathlib import Path

    save = Path(cfg.rerun.save) if cfg.rerun.save else None
    return [lambda ctx, manager: LiveView(ctx, manager, spawn=cfg.rerun.enabled, save_path=save)]
