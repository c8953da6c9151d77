"""Generate docs/parameters.md from the parameter metadata declared in the code.

Run `python -m companion.docgen docs/parameters.md` (or `make docs`); a test checks the committed
file is current, so the documentation can never drift from the code.
"""

from __future__ import annotations

import sys
from pathlib import Path

from companion.core.config import Config
from companion.core.params import ParamRegistry, format_value


def render(reg: ParamRegistry) -> str:
    lines = [
        "# Parameters",
        "",
        "Generated from the metadata next to the code that owns each parameter "
        "(`python -m companion.docgen docs/parameters.md`); do not edit by hand.",
        "",
        "Every parameter is an int32 or a float32 (the two types every MAVLink ground station "
        "handles), has a name of at most 16 characters, and is visible and settable from "
        "QGroundControl, MAVProxy, MAVSDK, pymavlink, the legacy monitor and "
        "`companion params`. Changes are validated, applied to the running threads at once, "
        "and persisted atomically to the parameter file.",
        "",
    ]
    groups: dict[str, list] = {}
    for spec in reg.specs():
        groups.setdefault(spec.group, []).append(spec)
    for group, specs in groups.items():
        lines += [f"## {group}", "", "| name | type | default | min | max | unit | notes | description |",
                  "|---|---|---|---|---|---|---|---|"]
        for s in specs:
            notes = ", ".join(n for n, on in (("read-only", s.read_only),
                                                ("reboot", s.reboot_required)) if on)
            lines.append(
                f"| `{s.name}` | {s.ptype.value} | {format_value(s.ptype, s.default)} | "
                f"{format_value(s.ptype, s.min)} | {format_value(s.ptype, s.max)} | {s.unit} | "
                f"{notes} | {s.description} |")
        lines.append("")
    return "\n".join(lines)


def reference() -> str:
    """The page for a vehicle with every row of its table switched on (the autopilot link's
    `AP_*` parameters are documented although the thesis aircraft has no autopilot)."""
    from companion.runtime import declared_registry
    from companion.vehicle import VEHICLE, fill_device_defaults

    cfg = fill_device_defaults(Config(), VEHICLE)
    for settings in cfg.devices.values():
        settings.enabled = True
    return render(declared_registry(cfg))


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m companion.docgen",
                                 description="Write the parameter reference (docs/parameters.md) "
                                             "from every parameter's metadata.")
    ap.add_argument("output", nargs="?", type=Path, help="file to write (default: stdout)")
    args = ap.parse_args(sys.argv[1:] if argv is None else argv)
    text = reference()
    if args.output is None:
        sys.stdout.write(text)
        return 0
    try:
        args.output.write_text(text, encoding="utf-8")
    except OSError as exc:
        sys.stderr.write(f"companion.docgen: cannot write {args.output}: {exc.strerror}\n")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
