"""The MAVLink console (SERIAL_CONTROL, device SHELL) as QGroundControl and MAVSDK drive it,
without sockets: messages are packed and parsed by pymavlink as a link would, then handled.

QGroundControl sends a typed line plus "\\n" with EXCLUSIVE | RESPOND | MULTI; MAVSDK splits a
command into 70-byte chunks, flags 0 on all but the last, which asks for a response.
"""

from __future__ import annotations

from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st
from support.synthetic_vehicle import SyntheticSource

from companion.core.clock import Clock
from companion.core.params import ParamRegistry, int_param
from companion.watchdog import ManagerCommand, RuntimeContext, ThreadManager
from gcs_bridge.bridge_params import BRIDGE_PARAMS
from gcs_bridge.dialect import mavlink
from gcs_bridge.runtime_view import BridgeCore
from gcs_bridge.services import console as console_mod
from gcs_bridge.services.console import (
    BANNER,
    CALL_OUTPUT_MAX_BYTES,
    DATA_BYTES,
    OUTPUT_MAX_BYTES,
    PROMPT,
    TRUNCATED,
    Console,
)

SHELL = int(mavlink.SERIAL_CONTROL_DEV_SHELL)
REPLY = int(mavlink.SERIAL_CONTROL_FLAG_REPLY)
RESPOND = int(mavlink.SERIAL_CONTROL_FLAG_RESPOND)
QGC_FLAGS = int(mavlink.SERIAL_CONTROL_FLAG_EXCLUSIVE | mavlink.SERIAL_CONTROL_FLAG_RESPOND
                | mavlink.SERIAL_CONTROL_FLAG_MULTI)
KINDS = ("imu", "gps", "servo", "estimator")


def make_core() -> BridgeCore:
    ctx = RuntimeContext(clock=Clock(), params=ParamRegistry(), vehicle_id=7)
    ctx.params.declare_all(BRIDGE_PARAMS)
    ctx.params.declare(int_param("TST_RO", 3, 0, 9, "", "A read-only value.", read_only=True))
    manager = ThreadManager(ctx, [SyntheticSource(k) for k in KINDS])
    return BridgeCore(ctx, manager)


def received(data: bytes, flags: int = QGC_FLAGS, device: int = SHELL,
             src: tuple[int, int] = (255, 190), count: int | None = None) -> Any:
    """A SERIAL_CONTROL as a link's parser delivers it."""
    msg = mavlink.MAVLink_serial_control_message(
        device, flags, 0, 0, len(data) if count is None else count,
        list(data[:DATA_BYTES].ljust(DATA_BYTES, b"\0")))
    return mavlink.MAVLink(None, 0, 0).parse_char(msg.pack(mavlink.MAVLink(None, *src)))


def text_of(replies: list[Any]) -> str:
    """The text of replies, after checking each is a well-formed shell reply."""
    out = b""
    for r in replies:
        back = mavlink.MAVLink(None, 0, 0).parse_char(r.pack(mavlink.MAVLink(None, 7, 1)))
        assert (back.device, back.flags, back.timeout, back.baudrate) == (SHELL, REPLY, 0, 0)
        assert 0 < back.count <= DATA_BYTES
        out += bytes(back.data[:back.count])
    text = out.decode("ascii")
    assert all(c == "\n" or " " <= c <= "~" for c in text)  # nothing a terminal interprets
    return text


class Client:
    """A QGroundControl console: one line per message, a new line after each answer."""

    def __init__(self, console: Console, src: tuple[int, int] = (255, 190)) -> None:
        self.console = console
        self.src = src

    def send(self, data: bytes, flags: int = QGC_FLAGS) -> str:
        return text_of(self.console.handle(received(data, flags, src=self.src)))

    def run(self, line: str) -> str:
        """The command's output, without its echo and the prompt (the greeting consumed)."""
        text = self.send(line.encode() + b"\n")
        if text.startswith(BANNER + PROMPT):
            text = text[len(BANNER + PROMPT):]
        assert text.startswith(line + "\n") and text.endswith(PROMPT)
        return text[len(line) + 1: -len(PROMPT)]


def posted(core: BridgeCore) -> list[ManagerCommand]:
    out = []
    while (cmd := core.manager.commands.get_nowait()) is not None:
        out.append(cmd)
    return out


# ------------------------------------------------------------------------------- commands
def test_first_answer_greets_then_echoes_answers_and_prompts() -> None:
    client = Client(Console(make_core()))
    text = client.send(b"help\n")
    assert text.startswith(BANNER + PROMPT + "help\n")
    assert text.endswith("\n" + PROMPT)
    for command in ("help", "threads", "restart NAME|ID", "param get NAME",
                    "param set NAME VALUE", "logs", "uptime"):
        assert f"  {command} " in text
    assert client.send(b"\n") == "\n" + PROMPT  # an empty line: just a new prompt


def test_threads_lists_every_thread() -> None:
    core = make_core()
    lines = Client(Console(core)).run("threads").splitlines()
    assert lines[0].split() == ["ID", "NAME", "STATE", "RATE_HZ", "RESTARTS", "LAST_ERROR"]
    rows = {int(line.split()[0]): line.split() for line in lines[1:]}
    statuses = core.manager.thread_status()
    assert len(rows) == len(statuses) == len(KINDS)
    for s in statuses:
        tid, name, state, rate, restarts, error = rows[s.thread_id]
        assert name == s.name and len(state) == 6 and state.startswith("E")
        assert (float(rate), int(restarts), error) == (0.0, 0, "-")


def test_param_get_and_set_go_through_the_registry() -> None:
    core = make_core()
    client = Client(Console(core))
    text = client.run("param get mav_b1_v_full")
    assert text.startswith("MAV_B1_V_FULL = 8.4 V (float32, default 8.4, range 0.1..100)\n")
    assert "Avionics battery voltage" in text
    assert client.run("param set MAV_B1_V_FULL 9.5") == "MAV_B1_V_FULL = 9.5 V\n"
    assert core.ctx.params.get("MAV_B1_V_FULL") == 9.5
    refused = client.run("param set MAV_B1_V_FULL 500")
    assert refused == "param set MAV_B1_V_FULL refused: out of range: 500 not in [0.1, 100] V\n"
    assert core.ctx.params.get("MAV_B1_V_FULL") == 9.5
    assert "refused: wrong type" in client.run("param set MAV_B_LOW_PCT 2.5")
    assert "refused: read-only" in client.run("param set TST_RO 4")
    assert "not a number" in client.run("param set MAV_B_LOW_PCT ten")
    assert "unknown parameter" in client.run("param get NOPE_X")
    assert client.run("param list MAV_B_") == "MAV_B_RAW_EMPTY = 80\nMAV_B_LOW_PCT = 20 %\n"
    assert client.run("param").startswith("usage: param get NAME")


def test_restart_posts_to_the_manager_and_reports_its_reply() -> None:
    core = make_core()
    client = Client(Console(core))
    gps = next(s for s in core.manager.thread_status() if s.name == "gps")
    assert client.run("restart GPS") == (f"restart of gps (id {gps.thread_id}) requested; "
                                         "the outcome follows a later prompt\n")
    assert "restart of imu (id 1)" in client.run("restart 1")
    commands = posted(core)
    assert [(c.kind, c.thread) for c in commands] == [("restart_thread", gps.thread_id),
                                                      ("restart_thread", 1)]
    assert commands[0].reply is not None and commands[1].reply is not None
    commands[0].reply(True, "")
    commands[1].reply(False, "unknown thread 1")
    assert client.send(b"\n") == ("\nrestart of gps: done\n"
                                  "restart of imu failed: unknown thread 1\n" + PROMPT)
    assert "no thread 'radar'" in client.run("restart radar")
    assert client.run("restart").startswith("usage:")
    assert posted(core) == []


def test_unknown_command_is_one_line_with_the_help_hint() -> None:
    assert Client(Console(make_core())).run("reboot now") == (
        "reboot: unknown command; type 'help' for the list\n")


def test_logs_and_uptime() -> None:
    core = make_core()
    flights = [("2024-05-01_101500", 3 * 1024 * 1024), ("2024-05-02_090000", 512)]
    client = Client(Console(core, flights=lambda: flights))
    assert client.run("logs").splitlines() == [
        "2024-05-01_101500    3.0 MiB", "2024-05-02_090000      512 B",
        "2 flight(s), 3.0 MiB"]
    assert Client(Console(core)).run("logs") == "logs: no flight directory is configured\n"
    assert Client(Console(core, flights=list)).run("logs") == "no flights\n"
    assert client.run("uptime").startswith("up 00:00:")


def test_a_failing_hook_is_reported_not_raised() -> None:
    def broken() -> list[tuple[str, int]]:
        raise OSError("disk gone")

    assert Client(Console(make_core(), flights=broken)).run("logs") == (
        "logs: failed: OSError: disk gone\n")


# ------------------------------------------------------------------------------- protocol
def test_a_line_split_over_two_messages() -> None:
    client = Client(Console(make_core()))
    assert client.send(b"param get MAV_B", flags=0) == ""  # MAVSDK's leading chunk: no RESPOND
    text = client.send(b"_LOW_PCT\n")
    assert text.startswith(BANNER + PROMPT + "param get MAV_B_LOW_PCT\nMAV_B_LOW_PCT = 20 %")


def test_a_mavsdk_command_longer_than_one_message() -> None:
    core = make_core()
    console = Console(core)
    command = b"param set MAV_B_LOW_PCT" + b" " * 60 + b"35\n"
    pieces = [command[i:i + DATA_BYTES] for i in range(0, len(command), DATA_BYTES)]
    assert len(pieces) == 2
    assert console.handle(received(pieces[0], flags=0)) == []
    text = text_of(console.handle(received(pieces[1], flags=RESPOND)))
    assert "MAV_B_LOW_PCT = 35 %\n" in text and core.ctx.params.get("MAV_B_LOW_PCT") == 35


def test_output_is_chunked_in_70_byte_replies() -> None:
    console = Console(make_core())
    replies = console.handle(received(b"help\n"))
    assert len(replies) > 3
    assert all(r.count == DATA_BYTES for r in replies[:-1])
    expected = BANNER + PROMPT + "help\n" + console_mod.HELP + PROMPT
    assert text_of(replies) == expected


def test_long_output_is_capped() -> None:
    flights = [(f"flight_{i:05d}", i) for i in range(3000)]
    client = Client(Console(make_core(), flights=lambda: flights))
    text = client.run("logs")
    assert len(text) <= OUTPUT_MAX_BYTES and text.endswith(TRUNCATED)
    batch = Client(Console(make_core(), flights=lambda: flights)).send(b"logs\nlogs\nlogs\n")
    assert len(batch) <= len(BANNER + PROMPT) + CALL_OUTPUT_MAX_BYTES + len(PROMPT)
    assert batch.endswith(TRUNCATED + PROMPT)


def test_terminal_line_editing() -> None:
    client = Client(Console(make_core()))
    client.send(b"\n")
    assert client.send(b"uptimX\x08e\r\n").startswith("uptime\nup ")  # "\r\n" is one end
    assert client.send(b"threads\rhelp\r").count(PROMPT) == 2
    assert client.send(b"param get\x03") == "^C\n" + PROMPT
    assert client.send(b"\x1b[Ahelp\n").startswith("[Ahelp\n[Ahelp: unknown command")
    assert client.send(b"\t\tuptime\n").startswith("  uptime\nup ")


def test_a_line_too_long_is_refused() -> None:
    client = Client(Console(make_core()))
    client.send(b"\n")
    for _ in range(10):
        assert client.send(b"x" * 60, flags=0) == ""
    text = client.send(b"help\n")
    assert text == f"\nline longer than {console_mod.LINE_MAX_BYTES} bytes: ignored\n" + PROMPT
    assert client.run("uptime").startswith("up ")


def test_clients_have_their_own_lines_and_closing_forgets_one() -> None:
    console = Console(make_core())
    qgc, other = Client(console, (255, 190)), Client(console, (1, 240))
    qgc.send(b"\n")
    other.send(b"\n")
    assert qgc.send(b"upt", flags=0) == "" and other.send(b"hel", flags=0) == ""
    assert qgc.send(b"ime\n").startswith("uptime\nup ")
    assert other.send(b"p\n").startswith("help\ncommands:")
    assert console.handle(received(b"", flags=0, src=(255, 190))) == []  # closes its console
    assert qgc.send(b"\n").startswith(BANNER)


def test_other_devices_replies_and_other_messages_are_ignored() -> None:
    console = Console(make_core())
    assert console.handle(received(b"help\n", device=int(mavlink.SERIAL_CONTROL_DEV_GPS1))) == []
    assert console.handle(received(b"help\n", flags=REPLY | RESPOND)) == []
    assert console.handle(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3)) == []
    assert console.handle(object()) == []
    assert console.handle(received(b"help\n", count=255)) != []  # count beyond 70: capped


@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=DATA_BYTES), flags=st.integers(0, 255),
       device=st.sampled_from([SHELL, SHELL, 0, 255]), count=st.integers(0, 255),
       src=st.tuples(st.integers(0, 255), st.integers(0, 255)))
def test_random_input_never_raises(data: bytes, flags: int, device: int, count: int,
                                   src: tuple[int, int]) -> None:
    console = FUZZ_CONSOLE
    replies = console.handle(received(data, flags, device, src, count))
    assert isinstance(replies, list)
    text_of(replies)


FUZZ_CONSOLE = Console(make_core(), flights=lambda: [("f", 1)])
