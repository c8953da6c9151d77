"""A MAVLink console: a small command shell over SERIAL_CONTROL, device SHELL (10).

QGroundControl's "MAVLink Console" and MAVSDK's Shell plugin were written for PX4's nsh, so
this console answers the way nsh does, which is what both display correctly:

- Input: QGroundControl sends each typed line plus "\\n" (flags EXCLUSIVE | RESPOND | MULTI;
  a line longer than 70 bytes is split, though QGroundControl resends its first 70 bytes
  instead of the rest). MAVSDK appends "\\n" if missing and splits at 70 bytes, flags 0 on
  every chunk but the last, which carries RESPOND only if the application listens. `count`
  gives the bytes used of `data`. A line therefore ends at "\\n" (also "\\r" or "\\r\\n", for
  terminals), may span messages, and is buffered per client (system, component).
- Output: SERIAL_CONTROL with device 10, flags REPLY, `count` bytes of at most 70 in `data`,
  as many messages as needed. QGroundControl splits what it receives at "\\n" and interprets
  ESC sequences (an incomplete one stalls its display), MAVSDK passes the bytes on up to the
  first NUL, so the output is printable ASCII and "\\n" only.
- Echo and prompt: neither client shows what was typed (QGroundControl clears its input
  field; nsh echoes), so each executed line is echoed after the prompt, and every answer
  ends with the prompt `PROMPT` without a newline, as nsh's "nsh> ".
- RESPOND: a line is executed whatever the flags (PX4 writes every chunk to its shell), but
  answered only when the message completing it asked for a response; a message without
  RESPOND and without data is a client closing its console, which forgets that session.

Commands change the vehicle (`param set`, `restart`): on a link that requires signing the
integrator calls `handle` only for signed messages; `handle` itself knows nothing of links.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

from companion.core.params import ParamError, ParamSpec, format_value
from companion.watchdog import ManagerCommand
from companion.watchdog.thread import ThreadStatus
from gcs_bridge.dialect import Message, RxMessage, mavlink
from gcs_bridge.runtime_view import BridgeCore

log = logging.getLogger(__name__)

DEVICE_SHELL = int(mavlink.SERIAL_CONTROL_DEV_SHELL)
FLAG_REPLY = int(mavlink.SERIAL_CONTROL_FLAG_REPLY)
FLAG_RESPOND = int(mavlink.SERIAL_CONTROL_FLAG_RESPOND)
DATA_BYTES = 70  # SERIAL_CONTROL.data
OUTPUT_MAX_BYTES = 16 * 1024  # per command: ~240 messages, a few seconds on a slow radio
CALL_OUTPUT_MAX_BYTES = 2 * OUTPUT_MAX_BYTES  # per received message (a pasted batch of lines)
LINE_MAX_BYTES = 512
SESSIONS_MAX = 16
ERROR_MAX_CHARS = 60
PROMPT = "companion> "
BANNER = "companion MAVLink console; type 'help' for the commands\n"
TRUNCATED = "... (truncated)\n"

#: The integrator's list of flight directories under the flight root: (name, size in bytes).
FlightList = Callable[[], list[tuple[str, int]]]

HELP = """commands:
  help                  this list
  threads               managed threads: id, name, state, rate, restarts, last error
  restart NAME|ID       restart one managed thread
  param get NAME        a parameter's value, range and description
  param set NAME VALUE  change a parameter (checked like any other change)
  param list [PREFIX]   parameters and values (those starting with PREFIX)
  logs                  flight directories and their sizes
  uptime                time since the bridge started
thread state: E enabled, I initialised, R running, P periodic, A alive at the last check,
F failed ('-' where not)
"""

_CTRL_C, _BACKSPACE, _DELETE, _TAB = 0x03, 0x08, 0x7F, 0x09
_OVERFLOW = "\0"  # stands for a line too long to keep (a real line never holds a NUL)


@dataclass
class _Session:
    """One client's console: the line being typed, and news for its next prompt."""

    line: bytearray = field(default_factory=bytearray)
    after_cr: bool = False
    overflow: bool = False
    greeted: bool = False
    notices: list[str] = field(default_factory=list)


def printable(text: str) -> str:
    """Text the clients display as sent: printable ASCII and newlines, anything else '?'."""
    return "".join(c if c == "\n" or " " <= c <= "~" else ("    " if c == "\t" else "?")
                   for c in text)


def cap(text: str, limit: int = OUTPUT_MAX_BYTES) -> str:
    """`text` cut to `limit` characters at a line end, saying so when it was."""
    if len(text) <= limit:
        return text
    cut = text.rfind("\n", 0, limit - len(TRUNCATED))
    return text[: cut + 1 if cut >= 0 else limit - len(TRUNCATED)] + TRUNCATED


def chunks(text: str) -> list[Message]:
    """SERIAL_CONTROL replies carrying `text`, at most 70 bytes each."""
    data = printable(text).encode("ascii")
    out: list[Message] = []
    for i in range(0, len(data), DATA_BYTES):
        part = data[i:i + DATA_BYTES]
        out.append(mavlink.MAVLink_serial_control_message(
            DEVICE_SHELL, FLAG_REPLY, 0, 0, len(part), list(part.ljust(DATA_BYTES, b"\0"))))
    return out


def _received_bytes(msg: RxMessage) -> bytes:
    """The `count` bytes a SERIAL_CONTROL carries (count beyond 70, or odd data, tolerated)."""
    raw = msg.data
    values = raw if isinstance(raw, bytes | bytearray) else bytes(int(b) & 0xFF for b in raw)
    return bytes(values[: max(0, min(int(msg.count), DATA_BYTES))])


def _size(n_bytes: int) -> str:
    for unit, scale in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n_bytes >= scale:
            return f"{n_bytes / scale:.1f} {unit}"
    return f"{n_bytes} B"


def _state(s: ThreadStatus) -> str:
    flags = (("E", s.enabled), ("I", s.initialised), ("R", s.running), ("P", s.in_periodic),
             ("A", s.alive), ("F", s.failed))
    return "".join(letter if on else "-" for letter, on in flags)


def _one_line(text: str, limit: int = ERROR_MAX_CHARS) -> str:
    text = " ".join(text.split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _with_unit(spec: ParamSpec, value: float | int) -> str:
    text = format_value(spec.ptype, value)
    return f"{text} {spec.unit}" if spec.unit else text


class Console:
    """Executes console lines for every client and answers with SERIAL_CONTROL replies.

    `handle` is called from the receive thread of any link (hence the lock) and never raises:
    whatever arrives, the worst answer is an error line and a prompt.
    """

    def __init__(self, core: BridgeCore, flights: FlightList | None = None, *,
                 prompt: str = PROMPT) -> None:
        self.core = core
        self.flights = flights
        self.prompt = prompt
        self._lock = threading.Lock()
        self._sessions: OrderedDict[tuple[int, int], _Session] = OrderedDict()

    # ------------------------------------------------------------------ protocol
    def handle(self, msg: RxMessage) -> list[Message]:
        """Replies to one received SERIAL_CONTROL ([] for another device, a reply, or
        a message that completes no line and asked for no response)."""
        try:
            return self._handle(msg)
        except Exception:  # a bug here must not reach the link's receive thread
            log.exception("console: input from %s dropped", _source(msg))
            return []

    def _handle(self, msg: RxMessage) -> list[Message]:
        get_type = getattr(msg, "get_type", None)
        if get_type is None or get_type() != "SERIAL_CONTROL" or int(msg.device) != DEVICE_SHELL:
            return []
        flags = int(msg.flags)
        if flags & FLAG_REPLY:  # another vehicle's output, never input
            return []
        data = _received_bytes(msg)
        key = _source(msg)
        respond = bool(flags & FLAG_RESPOND)
        with self._lock:
            if not respond and not data:
                self._sessions.pop(key, None)  # the client closed its console
                return []
            session = self._session(key)
        out = ""
        for line in self._lines(session, data):
            answer = self._run(session, line)  # executed even if nobody reads the answer
            if len(out) <= CALL_OUTPUT_MAX_BYTES:
                out += answer
        if len(out) > CALL_OUTPUT_MAX_BYTES:
            out = cap(out, CALL_OUTPUT_MAX_BYTES) + self.prompt
        if not respond:
            return []
        with self._lock:
            if not session.greeted:  # the first answer a client reads starts with a prompt
                session.greeted = True
                out = BANNER + self.prompt + out
        return chunks(out)

    def _session(self, key: tuple[int, int]) -> _Session:
        session = self._sessions.get(key)
        if session is None:
            session = self._sessions[key] = _Session()
            while len(self._sessions) > SESSIONS_MAX:
                self._sessions.popitem(last=False)
        self._sessions.move_to_end(key)
        return session

    def _lines(self, session: _Session, data: bytes) -> list[str | None]:
        """Complete lines in `data` (None: a line abandoned with Ctrl-C); the rest stays
        buffered. Backspace edits, other control bytes are dropped, a tab is a blank."""
        lines: list[str | None] = []
        with self._lock:
            for b in data:
                if b in (0x0A, 0x0D):
                    if b == 0x0A and session.after_cr:  # the "\n" of a "\r\n"
                        session.after_cr = False
                        continue
                    session.after_cr = b == 0x0D
                    text = session.line.decode("utf-8", "replace")
                    lines.append(_OVERFLOW if session.overflow else text)
                    session.line.clear()
                    session.overflow = False
                    continue
                session.after_cr = False
                if b == _CTRL_C:
                    session.line.clear()
                    session.overflow = False
                    lines.append(None)
                elif b in (_BACKSPACE, _DELETE):
                    if session.line:
                        del session.line[-1]
                elif b < 0x20 and b != _TAB:
                    continue
                elif len(session.line) >= LINE_MAX_BYTES:
                    session.overflow = True
                else:
                    session.line.append(0x20 if b == _TAB else b)
        return lines

    def _run(self, session: _Session, line: str | None) -> str:
        """Echo, answer, news and prompt for one line."""
        if line is None:
            answer = "^C\n"
        elif line == _OVERFLOW:
            answer = f"\nline longer than {LINE_MAX_BYTES} bytes: ignored\n"
        else:
            answer = line + "\n" + cap(self._execute(line, session))
        with self._lock:
            news, session.notices = session.notices, []
        return answer + "".join(news) + self.prompt

    # ------------------------------------------------------------------ commands
    def execute(self, line: str) -> str:
        """The output of one command line ("" for a blank one), each line ending in "\\n"."""
        return self._execute(line, None)

    def _execute(self, line: str, session: _Session | None) -> str:
        words = line.split()
        if not words:
            return ""
        cmd, args = words[0].lower(), words[1:]
        try:
            if cmd == "help":
                return HELP
            if cmd == "threads":
                return self._threads()
            if cmd == "restart":
                return self._restart(args, session)
            if cmd == "param":
                return self._param(args)
            if cmd == "logs":
                return self._logs()
            if cmd == "uptime":
                return self._uptime()
        except Exception as exc:  # one command's failure is reported, the console carries on
            log.exception("console: %r failed", line)
            return f"{cmd}: failed: {_one_line(f'{type(exc).__name__}: {exc}')}\n"
        return f"{_one_line(words[0], 32)}: unknown command; type 'help' for the list\n"

    def _threads(self) -> str:
        statuses = self.core.manager.thread_status()
        if not statuses:
            return "no managed threads\n"
        width = max(len("NAME"), *(len(s.name) for s in statuses))
        lines = [f"{'ID':>3} {'NAME':<{width}} STATE  {'RATE_HZ':>8} {'RESTARTS':>8} LAST_ERROR"]
        for s in statuses:
            lines.append(f"{s.thread_id:>3} {s.name:<{width}} {_state(s)} "
                         f"{s.measured_rate_hz:>8.1f} {s.restarts:>8} "
                         f"{_one_line(s.last_error) if s.last_error else '-'}")
        return "\n".join(lines) + "\n"

    def _find_thread(self, key: str) -> ThreadStatus | None:
        statuses = self.core.manager.thread_status()
        if key.isdigit():
            by_id = [s for s in statuses if s.thread_id == int(key)]
            if by_id:
                return by_id[0]
        by_name = [s for s in statuses if s.name.lower() == key.lower()]
        return by_name[0] if by_name else None

    def _restart(self, args: list[str], session: _Session | None) -> str:
        if len(args) != 1:
            return "usage: restart NAME|ID (see 'threads')\n"
        status = self._find_thread(args[0])
        if status is None:
            return f"restart: no thread {_one_line(args[0], 32)!r} (see 'threads')\n"
        name, tid = status.name, status.thread_id

        def reply(ok: bool, reason: str) -> None:  # runs in the manager's (main) thread
            note = (f"restart of {name}: done\n" if ok
                    else f"restart of {name} failed: {_one_line(reason)}\n")
            log.info("console: %s", note.strip())
            if session is not None:
                with self._lock:
                    session.notices.append(note)

        if not self.core.manager.post(ManagerCommand("restart_thread", tid, reply=reply)):
            return "restart: the manager's queue is full; try again\n"
        log.info("console: restart of thread %s (id %d) posted to the manager", name, tid)
        return f"restart of {name} (id {tid}) requested; the outcome follows a later prompt\n"

    def _param(self, args: list[str]) -> str:
        sub = args[0].lower() if args else ""
        params = self.core.ctx.params
        if sub == "get" and len(args) == 2:
            name = args[1].upper()
            try:
                spec, current = params.spec(name), params.get(name)
            except ParamError as exc:
                return f"param get: {exc.name}: {exc.reason}\n"
            notes = [spec.ptype.value, f"default {format_value(spec.ptype, spec.default)}",
                     f"range {format_value(spec.ptype, spec.min)}.."
                     f"{format_value(spec.ptype, spec.max)}"]
            notes += [n for n, on in (("read-only", spec.read_only),
                                      ("reboot required", spec.reboot_required)) if on]
            text = f"{name} = {_with_unit(spec, current)} ({', '.join(notes)})\n"
            return text + (f"  {spec.description}\n" if spec.description else "")
        if sub == "set" and len(args) == 3:
            name, text = args[1].upper(), args[2]
            value: int | float
            try:
                value = int(text)
            except ValueError:
                try:
                    value = float(text)
                except ValueError:
                    return f"param set: {_one_line(text, 32)!r} is not a number\n"
            try:
                new = params.set(name, value)
            except ParamError as exc:
                return f"param set {exc.name} refused: {exc.reason}\n"
            log.info("console: %s set to %s", name, new)
            return f"{name} = {_with_unit(params.spec(name), new)}\n"
        if sub == "list" and len(args) <= 2:
            prefix = args[1].upper() if len(args) == 2 else ""
            values = params.snapshot()
            lines = [f"{s.name} = {_with_unit(s, values[s.name])}" for s in params.specs()
                     if s.name.startswith(prefix) and s.name in values]
            return "\n".join(lines) + "\n" if lines else f"no parameter starts with {prefix}\n"
        return "usage: param get NAME | param set NAME VALUE | param list [PREFIX]\n"

    def _logs(self) -> str:
        if self.flights is None:
            return "logs: no flight directory is configured\n"
        flights = self.flights()
        if not flights:
            return "no flights\n"
        width = max(len(name) for name, _ in flights)
        total = sum(max(0, int(size)) for _, size in flights)
        lines = [f"{name:<{width}} {_size(max(0, int(size))):>10}" for name, size in flights]
        lines.append(f"{len(flights)} flight(s), {_size(total)}")
        return "\n".join(lines) + "\n"

    def _uptime(self) -> str:
        elapsed_s = max(0, self.core.ctx.clock.monotonic_ns() - self.core.boot_mono_ns) // 10**9
        days, rest = divmod(int(elapsed_s), 86_400)
        hours, rest = divmod(rest, 3600)
        minutes, seconds = divmod(rest, 60)
        return (f"up {f'{days}d ' if days else ''}{hours:02d}:{minutes:02d}:{seconds:02d}"
                f" (time_boot_ms {self.core.time_boot_ms()})\n")


def _source(msg: RxMessage) -> tuple[int, int]:
    try:
        return int(msg.get_srcSystem()), int(msg.get_srcComponent())
    except Exception:
        return 0, 0
