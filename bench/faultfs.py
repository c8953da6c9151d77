"""FaultFs: a FUSE passthrough file system that turns slow, read-only or full on command.

Why: the fault campaign (`bench/faults_bench.py`) must put the runtime's log directory on a
disk that misbehaves *while files are open for writing*. A tmpfs can be made small (full disk)
but not slow (dm-delay needs device-mapper, absent in containers), and remounting it read-only
while files are open fails with EBUSY. A FUSE mount that forwards every call to a backing
directory, and fails or delays the calls we choose, covers all three on any Linux machine with
/dev/fuse.

The file system runs in its own process (`python bench/faultfs.py serve BACKING MOUNT
--control DIR`) so a flight under test never shares a process, a GIL or a signal handler with
it. libfuse runs it multi-threaded: one fsync sleeping for a second does not hold up writes to
the other files (the kernel still serialises operations on one inode, as a real disk would).

Faults (all off by default), switchable while mounted:

- ``fsync_delay_s``: every fsync, fdatasync and directory fsync sleeps that long first. FLUSH,
  which the kernel sends on every close(2), is not delayed: it is not a sync.
- ``write_delay_s``: every write request sleeps that long first (a request is at most 128 KiB).
- ``readonly``: every call that would change the disk (write, create, open for writing,
  truncate, mkdir, mknod, unlink, rmdir, rename, link, symlink, chmod, chown, utimens) fails
  with EROFS, including writes on files opened before the switch, as after an ext4
  ``errors=remount-ro``. Reads, stat, readdir, fsync and close still work.
- ``enospc``: writes and anything that allocates (create, mkdir, mknod, link, symlink) fail
  with ENOSPC; deleting still works, as on a full disk.

Control: the server polls ``<control>/faults.json`` (every 20 ms), a JSON object holding the
whole fault state (missing keys are off); it answers in ``<control>/state.json`` (the faults in
force, the generation it acknowledges, counters) and logs to ``<control>/server.log``. The
control directory is outside the mount so switching a fault never goes through the faulty
file system. From Python use `FaultFs.set`; by hand::

    python bench/faultfs.py set --control DIR readonly=1 fsync_delay_s=0.5

Needs: Linux, /dev/fuse, the `mfusepy` package (ctypes bindings for libfuse 2 and 3) and
libfuse (Debian: ``fuse3 libfuse3-3``); `unavailable_reason` says which is missing so a
benchmark row can say "skipped" instead of failing.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import importlib.util
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from ctypes.util import find_library
from pathlib import Path
from typing import Any

log = logging.getLogger("faultfs")

DEFAULT_FAULTS: dict[str, Any] = {
    "fsync_delay_s": 0.0,
    "write_delay_s": 0.0,
    "readonly": False,
    "enospc": False,
}
POLL_S = 0.02  # control file polling period of the server
STATE_PERIOD_S = 0.2  # counters are republished at most this often


class FaultFsUnavailable(RuntimeError):
    """FUSE cannot be used here (no library, no device, no permission, mount failed)."""


def _fusermount() -> str | None:
    return shutil.which("fusermount3") or shutil.which("fusermount")


def unavailable_reason() -> str | None:
    """Why FaultFs cannot run on this machine, or None. Cheap checks only; a mount can still
    fail (a container without CAP_SYS_ADMIN), which `FaultFs.__enter__` reports the same way."""
    if not sys.platform.startswith("linux"):
        return f"FUSE fault injection needs Linux, not {sys.platform}"
    if not os.path.exists("/dev/fuse"):
        return "/dev/fuse does not exist (no FUSE in this kernel or container)"
    if not os.access("/dev/fuse", os.R_OK | os.W_OK):
        return "no permission to open /dev/fuse"
    if importlib.util.find_spec("mfusepy") is None:
        return "Python package mfusepy is not installed (pip install mfusepy)"
    if not (find_library("fuse3") or find_library("fuse")):
        return "libfuse is not installed (apt-get install fuse3 libfuse3-3)"
    if os.geteuid() != 0 and _fusermount() is None:
        return "neither root nor fusermount3/fusermount to mount as a user"
    return None


def _write_json_atomic(path: Path, obj: dict[str, Any]) -> None:
    """Readers (the other process) see the old file or the new one, never half of one."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    tmp.write_text(json.dumps(obj, sort_keys=True), encoding="utf-8")
    os.replace(tmp, path)


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        value = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return value if isinstance(value, dict) else None


def normalize_faults(raw: dict[str, Any]) -> dict[str, Any]:
    """The whole fault state from a (partial) mapping; ValueError on an unknown key or value."""
    unknown = set(raw) - set(DEFAULT_FAULTS) - {"generation"}
    if unknown:
        raise ValueError(f"unknown fault(s) {sorted(unknown)}; known: {sorted(DEFAULT_FAULTS)}")
    out = dict(DEFAULT_FAULTS)
    for key in DEFAULT_FAULTS:
        if key not in raw:
            continue
        v = raw[key]
        if key.endswith("_s"):
            f = float(v)
            if not 0.0 <= f <= 3600.0:
                raise ValueError(f"{key} must be within 0..3600 s, got {v!r}")
            out[key] = f
        else:
            if isinstance(v, str):
                v = v.strip().lower() in ("1", "true", "yes", "on")
            out[key] = bool(v)
    return out


# ------------------------------------------------------------------------------ the server
class _State:
    """Fault switches and counters shared by the FUSE threads and the control thread."""

    def __init__(self, control: Path, faults: dict[str, Any]) -> None:
        self.control = control
        self.faults = dict(faults)
        self.generation = 0
        self.cond = threading.Condition()
        self.counts: dict[str, float] = {}
        self.fsync_paths: dict[str, int] = {}
        self.errors: list[str] = []
        self.mounted = False
        self._dirty = True

    def count(self, key: str, n: float = 1) -> None:
        with self.cond:
            self.counts[key] = self.counts.get(key, 0) + n
            self._dirty = True

    def delay(self, key: str) -> float:
        """Sleep for the configured delay; a change of the setting (an unmount resets it)
        shortens or lengthens the sleep still under way, so nothing outlives its fault."""
        start = time.monotonic()
        with self.cond:
            while True:
                left = start + float(self.faults[key]) - time.monotonic()
                if left <= 0:
                    break
                self.cond.wait(left)
        return time.monotonic() - start

    def apply(self, raw: dict[str, Any]) -> None:
        try:
            faults = normalize_faults(raw)
        except (ValueError, TypeError) as exc:
            with self.cond:
                self.errors = (self.errors + [f"control: {exc}"])[-10:]
                self._dirty = True
            log.error("control file refused: %s", exc)
            return
        with self.cond:
            self.faults = faults
            self.generation = int(raw.get("generation", self.generation + 1))
            self._dirty = True
            self.cond.notify_all()
        log.info("faults now %s (generation %d)", faults, self.generation)

    def publish(self, force: bool = False) -> None:
        with self.cond:
            if not (self._dirty or force):
                return
            self._dirty = False
            state = {"pid": os.getpid(), "generation": self.generation, "faults": self.faults,
                     "mounted": self.mounted, "counts": dict(self.counts),
                     "fsync_paths": dict(self.fsync_paths), "errors": list(self.errors)}
        _write_json_atomic(self.control / "state.json", state)


class FaultOps:
    """The passthrough operations (mfusepy's `Operations` protocol, duck-typed so this module
    imports without mfusepy). Paths are relative to the mount; OSError(errno) is the answer."""

    use_ns = True  # times as integer nanoseconds (mfusepy's float seconds are deprecated)

    def __init__(self, backing: Path, state: _State) -> None:
        self.root = str(backing)
        self.state = state

    def _p(self, path: str) -> str:
        return self.root + path

    def _refuse(self, op: str, allocates: bool = True) -> None:
        faults = self.state.faults
        if faults["readonly"]:
            self.state.count("erofs")
            self.state.count(f"erofs_{op}")
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        if allocates and faults["enospc"]:
            self.state.count("enospc")
            self.state.count(f"enospc_{op}")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    # -- lifecycle
    def init(self, path: str) -> None:
        with self.state.cond:
            self.state.mounted = True
        self.state.publish(force=True)
        log.info("mounted")

    def destroy(self, path: str) -> None:
        with self.state.cond:
            self.state.mounted = False
        self.state.publish(force=True)

    # -- reading
    def getattr(self, path: str, fh: int | None = None) -> dict[str, Any]:
        st = os.fstat(fh) if fh else os.lstat(self._p(path))
        return {
            "st_mode": st.st_mode, "st_nlink": st.st_nlink, "st_uid": st.st_uid,
            "st_gid": st.st_gid, "st_size": st.st_size, "st_blocks": st.st_blocks,
            "st_blksize": st.st_blksize, "st_atime": st.st_atime_ns,
            "st_mtime": st.st_mtime_ns, "st_ctime": st.st_ctime_ns,
        }

    def access(self, path: str, amode: int) -> int:
        if amode & os.W_OK and self.state.faults["readonly"]:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        if not os.access(self._p(path), amode):
            raise OSError(errno.EACCES, os.strerror(errno.EACCES))
        return 0

    def readdir(self, path: str, fh: int) -> list[str]:
        return [".", "..", *os.listdir(self._p(path))]

    def readlink(self, path: str) -> str:
        return os.readlink(self._p(path))

    def statfs(self, path: str) -> dict[str, int]:
        sv = os.statvfs(self._p(path))
        return {k: getattr(sv, k) for k in ("f_bavail", "f_bfree", "f_blocks", "f_bsize",
                                            "f_favail", "f_ffree", "f_files", "f_flag",
                                            "f_frsize", "f_namemax")}

    def open(self, path: str, flags: int) -> int:
        if (flags & os.O_ACCMODE) != os.O_RDONLY or flags & os.O_TRUNC:
            self._refuse("open", allocates=False)
        return os.open(self._p(path), flags)

    def read(self, path: str, size: int, offset: int, fh: int) -> bytes:
        return os.pread(fh, size, offset)

    # -- writing
    def create(self, path: str, mode: int, flags: int) -> int:
        self._refuse("create")
        return os.open(self._p(path), flags | os.O_CREAT, mode)

    def write(self, path: str, data: bytes, offset: int, fh: int) -> int:
        if self.state.faults["write_delay_s"] > 0:
            self.state.count("write_delayed_s", self.state.delay("write_delay_s"))
        self._refuse("write")
        n = os.pwrite(fh, data, offset)  # O_APPEND files append whatever the offset
        self.state.count("writes")
        self.state.count("bytes_written", n)
        return n

    def truncate(self, path: str, length: int, fh: int | None = None) -> int:
        self._refuse("truncate", allocates=False)
        if fh:
            os.ftruncate(fh, length)
        else:
            os.truncate(self._p(path), length)
        return 0

    def flush(self, path: str, fh: int) -> int:
        return 0  # close(2): nothing buffered here, and not a sync (see the module docstring)

    def release(self, path: str, fh: int) -> int:
        os.close(fh)
        return 0

    def _sync_delay(self, path: str) -> None:
        self.state.count("fsyncs")
        if self.state.faults["fsync_delay_s"] > 0:
            self.state.count("fsync_delayed_s", self.state.delay("fsync_delay_s"))
            self.state.count("fsyncs_delayed")
            with self.state.cond:
                self.state.fsync_paths[path] = self.state.fsync_paths.get(path, 0) + 1

    def fsync(self, path: str, datasync: int, fh: int) -> int:
        self._sync_delay(path)
        if datasync:
            os.fdatasync(fh)
        else:
            os.fsync(fh)
        return 0

    def fsyncdir(self, path: str, datasync: int, fh: int) -> int:
        self._sync_delay(path + "/" if path != "/" else path)
        fd = os.open(self._p(path), os.O_RDONLY | os.O_DIRECTORY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        return 0

    def mkdir(self, path: str, mode: int) -> int:
        self._refuse("mkdir")
        os.mkdir(self._p(path), mode)
        return 0

    def mknod(self, path: str, mode: int, dev: int) -> int:
        self._refuse("mknod")
        os.mknod(self._p(path), mode, dev)
        return 0

    def unlink(self, path: str) -> int:
        self._refuse("unlink", allocates=False)
        os.unlink(self._p(path))
        return 0

    def rmdir(self, path: str) -> int:
        self._refuse("rmdir", allocates=False)
        os.rmdir(self._p(path))
        return 0

    def rename(self, old: str, new: str) -> int:
        self._refuse("rename", allocates=False)
        os.rename(self._p(old), self._p(new))
        return 0

    def symlink(self, target: str, source: str) -> int:
        """`target` is the new link (a path in the mount), `source` what it points to."""
        self._refuse("symlink")
        os.symlink(source, self._p(target))
        return 0

    def link(self, target: str, source: str) -> int:
        self._refuse("link")
        os.link(self._p(source), self._p(target))
        return 0

    def chmod(self, path: str, mode: int) -> int:
        self._refuse("chmod", allocates=False)
        os.chmod(self._p(path), mode)
        return 0

    def chown(self, path: str, uid: int, gid: int) -> int:
        self._refuse("chown", allocates=False)
        os.chown(self._p(path), uid, gid, follow_symlinks=False)
        return 0

    def utimens(self, path: str, times: tuple[int, int] | None = None) -> int:
        self._refuse("utimens", allocates=False)
        if times is None:
            os.utime(self._p(path))
        else:
            os.utime(self._p(path), ns=(int(times[0]), int(times[1])))
        return 0


def _control_loop(state: _State, stop: threading.Event) -> None:
    """Poll the control file; apply a new content; republish counters when they changed."""
    path = state.control / "faults.json"
    seen: bytes | None = None
    next_publish = 0.0
    while not stop.wait(POLL_S):
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            data = None
        except OSError as exc:
            log.error("control file: %s", exc)
            data = seen
        if data is not None and data != seen:
            seen = data
            try:
                raw = json.loads(data)
                if not isinstance(raw, dict):
                    raise ValueError("not a JSON object")
            except ValueError as exc:
                state.apply({"__bad__": str(exc)})  # recorded in state.errors
            else:
                state.apply(raw)
            state.publish(force=True)
        now = time.monotonic()
        if now >= next_publish:
            next_publish = now + STATE_PERIOD_S
            state.publish()


def serve(backing: Path, mount: Path, control: Path, faults: dict[str, Any]) -> int:
    """Run the file system in the foreground until unmounted (or SIGTERM/SIGINT)."""
    control.mkdir(parents=True, exist_ok=True)
    state = _State(control, faults)
    state.publish(force=True)
    try:
        import mfusepy
    except (ImportError, OSError) as exc:  # OSError: mfusepy found no libfuse
        print(f"faultfs: cannot load mfusepy/libfuse: {exc}", file=sys.stderr)
        return 3
    stop = threading.Event()
    poller = threading.Thread(target=_control_loop, args=(state, stop), name="faultfs-control",
                              daemon=True)
    poller.start()
    try:
        # foreground: this process is the server; multi-threaded (no `nothreads`) so a sleeping
        # fsync does not block the other files; `fsname` shows in /proc/mounts.
        mfusepy.FUSE(FaultOps(backing.resolve(), state), str(mount), foreground=True,
                     nothreads=False, fsname=f"faultfs:{backing}", default_permissions=True)
    except RuntimeError as exc:
        print(f"faultfs: FUSE failed: {exc}", file=sys.stderr)
        return 4
    finally:
        stop.set()
        with state.cond:
            state.mounted = False
        state.publish(force=True)
    return 0


# ------------------------------------------------------------------------------ the client
class FaultFs:
    """Mount `backing` at `mount` through a faultfs server process; faults off at first.

    `with FaultFs(backing, mount) as fs: ... fs.set(readonly=True) ...`. Entering waits
    (bounded) until the kernel sees the mount; exiting switches every fault off (so a sleeping
    fsync ends), unmounts (fusermount -u, lazily if busy) and stops the server, all bounded.
    Raises FaultFsUnavailable when FUSE cannot be used here.
    """

    def __init__(self, backing: Path, mount: Path, *, control: Path | None = None,
                 ready_timeout_s: float = 10.0) -> None:
        self.backing = Path(backing)
        self.mount = Path(mount)
        self.control = Path(control) if control else Path(tempfile.mkdtemp(prefix="faultfs-"))
        self.ready_timeout_s = ready_timeout_s
        self.proc: subprocess.Popen[bytes] | None = None
        self.faults: dict[str, Any] = dict(DEFAULT_FAULTS)
        self._generation = 0
        self.last_state: dict[str, Any] = {}

    def __enter__(self) -> FaultFs:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _server_log(self) -> str:
        try:
            text = (self.control / "server.log").read_text(errors="replace")
        except OSError:
            return ""
        return text.strip()[-300:]

    def start(self) -> None:
        reason = unavailable_reason()
        if reason:
            raise FaultFsUnavailable(reason)
        try:
            self.backing.mkdir(parents=True, exist_ok=True)
            self.mount.mkdir(parents=True, exist_ok=True)
            self.control.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise FaultFsUnavailable(f"cannot prepare the directories: {exc}") from exc
        with contextlib.suppress(FileNotFoundError):
            (self.control / "state.json").unlink()
        _write_json_atomic(self.control / "faults.json", {**self.faults, "generation": 0})
        with open(self.control / "server.log", "ab") as errlog:
            self.proc = subprocess.Popen(
                [sys.executable, str(Path(__file__).resolve()), "serve", str(self.backing),
                 str(self.mount), "--control", str(self.control)],
                stdin=subprocess.DEVNULL, stdout=errlog, stderr=errlog, start_new_session=True)
        deadline = time.monotonic() + self.ready_timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise FaultFsUnavailable(f"faultfs server exited with {self.proc.returncode}: "
                                         f"{self._server_log() or 'no message'}")
            st = _read_json(self.control / "state.json")
            if st and st.get("mounted") and os.path.ismount(self.mount):
                self.last_state = st
                return
            time.sleep(0.05)
        self._stop_server()
        raise FaultFsUnavailable(f"not mounted within {self.ready_timeout_s:g} s: "
                                 f"{self._server_log() or 'no message'}")

    def set(self, timeout_s: float = 5.0, **faults: Any) -> dict[str, Any]:
        """Switch faults (the others keep their setting); returns once the server applied it.

        Raises TimeoutError when the server did not acknowledge within `timeout_s`."""
        new = normalize_faults({**self.faults, **faults})
        self._generation += 1
        gen = self._generation
        _write_json_atomic(self.control / "faults.json", {**new, "generation": gen})
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            st = _read_json(self.control / "state.json")
            if st and st.get("generation") == gen:
                self.faults = new
                self.last_state = st
                return st
            if self.proc is not None and self.proc.poll() is not None:
                break
            time.sleep(POLL_S / 2)
        raise TimeoutError(f"faultfs did not apply {faults} within {timeout_s:g} s "
                           f"({self._server_log()})")

    def stats(self, fresh: bool = True) -> dict[str, Any]:
        """The server's state: faults, counters (fsyncs, fsyncs_delayed, fsync_delayed_s,
        writes, bytes_written, erofs, enospc, per-operation erofs_<op>...), fsync_paths (path
        -> delayed fsyncs). `fresh`: re-applies the same faults so the server publishes now
        (its periodic copy may be 0.2 s old); otherwise, or if it does not answer, the last."""
        if fresh and self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(TimeoutError, OSError):
                return self.set(timeout_s=2.0)
        st = _read_json(self.control / "state.json")
        if st:
            self.last_state = st
        return self.last_state

    def _unmount(self, lazy: bool) -> bool:
        tool = _fusermount()
        if tool is not None:
            cmd = [tool, "-u", *(["-z"] if lazy else []), str(self.mount)]
        else:
            cmd = ["umount", *(["-l"] if lazy else []), str(self.mount)]
        try:
            return subprocess.run(cmd, capture_output=True, timeout=5.0).returncode == 0
        except (OSError, subprocess.TimeoutExpired):
            return False

    def _stop_server(self, grace_s: float = 5.0) -> None:
        """Wait for the server to leave on its own (after an unmount), then SIGTERM (libfuse
        leaves its loop and unmounts), then SIGKILL: each wait bounded."""
        proc = self.proc
        if proc is None:
            return
        for sig, wait_s in ((None, grace_s), (signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0)):
            if sig is not None and proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.send_signal(sig)
            try:
                proc.wait(wait_s)
                break
            except subprocess.TimeoutExpired:
                continue

    def close(self) -> None:
        """Faults off, unmount (lazy when busy), stop the server: bounded, never raises."""
        if self.proc is None:
            return
        if self.proc.poll() is None:
            with contextlib.suppress(TimeoutError, OSError):
                self.set(timeout_s=2.0, **DEFAULT_FAULTS)
        self.stats(fresh=False)
        if self._unmount(lazy=False):
            self._stop_server()
        else:
            # busy (a file still open there): detach it now; the server would only leave once
            # the last file is closed, so it is told to stop after a short grace
            log.warning("faultfs: %s busy, unmounting lazily", self.mount)
            self._unmount(lazy=True)
            self._stop_server(grace_s=0.5)
        if os.path.ismount(self.mount):  # a server killed without unmounting leaves it dead
            self._unmount(lazy=True)
        self.proc = None


# ------------------------------------------------------------------------------ command line
def _parse_assignments(items: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"expected KEY=VALUE, got {item!r}")
        out[key.strip()] = value.strip()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    sv = sub.add_parser("serve", help="run the file system (foreground) until unmounted")
    sv.add_argument("backing", type=Path)
    sv.add_argument("mount", type=Path)
    sv.add_argument("--control", type=Path, required=True, help="directory of faults.json")
    sv.add_argument("faults", nargs="*", help="initial faults, KEY=VALUE")
    st = sub.add_parser("set", help="switch faults of a running server (KEY=VALUE...)")
    st.add_argument("--control", type=Path, required=True)
    st.add_argument("faults", nargs="*")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s faultfs %(message)s")
    if args.cmd == "serve":
        faults = normalize_faults(_parse_assignments(args.faults))
        return serve(args.backing, args.mount, args.control, faults)
    cur = _read_json(args.control / "faults.json") or {}
    new = normalize_faults({**{k: v for k, v in cur.items() if k in DEFAULT_FAULTS},
                            **_parse_assignments(args.faults)})
    _write_json_atomic(args.control / "faults.json",
                       {**new, "generation": int(cur.get("generation", 0)) + 1})
    print(json.dumps(new))
    return 0


if __name__ == "__main__":
    sys.exit(main())
