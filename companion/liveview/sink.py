"""Where a rerun stream goes: a spawned viewer, an ``.rrd`` file, a server for web browsers.

Each live view or replay gets its own `RecordingStream` (never rerun's global one), so two views
in one process, or a test next to a flight, do not share state.
"""

from __future__ import annotations

import logging
import uuid
from dataclasses import dataclass
from pathlib import Path

import rerun as rr

from companion.liveview.entities import log_static_layout

__all__ = ["APPLICATION_ID", "Recording", "ViewerError", "open_recording"]

log = logging.getLogger(__name__)

APPLICATION_ID = "uav-companion"
DEFAULT_GRPC_PORT = 9876
DEFAULT_WEB_PORT = 9090


class ViewerError(RuntimeError):
    """The rerun viewer, file or server could not be set up; the message says which."""


@dataclass
class Recording:
    """An open stream and where it goes; `close()` flushes and detaches every sink."""

    stream: rr.RecordingStream
    save_path: Path | None
    url: str | None  # gRPC URL a viewer can connect to (served)
    web_url: str | None
    spawned: bool = False

    def close(self, timeout_s: float = 10.0) -> None:
        """Flush (waiting at most `timeout_s`) and detach every sink.

        Raises ViewerError when the data could not be delivered (a spawned viewer that never
        came up, for instance on a machine without a display); the sinks are detached anyway.
        """
        error: Exception | None = None
        try:
            self.stream.flush(timeout_sec=timeout_s)
        except Exception as exc:  # rerun raises RuntimeError with its own reason
            error = exc
        finally:
            self.stream.disconnect()
        if error is not None:
            hint = (" (the spawned viewer is not running: no display? use --rerun-save PATH or "
                    "--serve)" if self.spawned else "")
            raise ViewerError(f"rerun stream not fully delivered: {error}{hint}") from error


def open_recording(*, spawn: bool = False, save_path: Path | str | None = None, serve: bool = False,
                   name: str = "flight", grpc_port: int = DEFAULT_GRPC_PORT,
                   web_port: int = DEFAULT_WEB_PORT, open_browser: bool = False,
                   serve_host: str = "0.0.0.0") -> Recording:
    """A stream with its sinks set and the static layout logged.

    At least one of `spawn`, `save_path` and `serve` must be given. `serve` hosts a gRPC server
    on `serve_host`:`grpc_port` and rerun's web viewer on `web_port`; viewers on other machines
    (a laptop on the ground) connect to it, hence all interfaces by default.
    """
    if not (spawn or save_path or serve):
        raise ViewerError("no rerun destination: give spawn, save_path or serve")
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=uuid.uuid4())
    # Only our own timeline: rerun's wall-clock "log_time" would differ on every replay.
    rec.set_log_time_enabled(False)
    rec.set_log_tick_enabled(False)
    sinks: list[object] = []
    path: Path | None = None
    url = web_url = None
    if save_path:
        path = Path(save_path)
        if path.parent and not path.parent.is_dir():
            raise ViewerError(f"--rerun-save {path}: directory {path.parent} does not exist")
        try:
            sinks.append(rr.FileSink(path))
        except Exception as exc:
            raise ViewerError(f"--rerun-save {path}: {exc}") from exc
    if spawn:
        try:
            rr.spawn(port=grpc_port, connect=False)
        except Exception as exc:
            raise ViewerError(f"cannot spawn the rerun viewer: {exc}") from exc
        sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{grpc_port}/proxy"))
    if serve:
        try:
            server = rr.GrpcServerSink(bind_ip=serve_host, port=grpc_port)
            url = server.uri
            sinks.append(server)
        except Exception as exc:
            raise ViewerError(f"cannot serve rerun on {serve_host}:{grpc_port}: {exc}") from exc
    try:
        rec.set_sinks(*sinks)  # type: ignore[arg-type]
    except Exception as exc:
        raise ViewerError(f"cannot start the rerun stream: {exc}") from exc
    if serve and url is not None:
        try:
            rr.serve_web_viewer(web_port=web_port, open_browser=open_browser, connect_to=url)
            web_url = f"http://{'127.0.0.1' if serve_host == '0.0.0.0' else serve_host}:{web_port}"
        except Exception as exc:
            log.warning("rerun web viewer not started on port %d: %s (gRPC at %s)", web_port, exc, url)
    rec.send_recording_name(name)
    log_static_layout(rec)
    return Recording(rec, path, url, web_url, spawned=spawn)
