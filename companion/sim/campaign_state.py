"""What a campaign directory remembers: which flights were flown, how, and where.

A campaign may be stopped at any moment (Ctrl-C, a lost cluster, a driver killed with SIGKILL)
and the same command run again must fly only what is missing. So the state is not one file
rewritten as flights finish but one small completion marker per flight, `runs/NNNN.json`,
written after the flight's directory is in place and written atomically (a temporary name, then
a rename): a flight without a marker is not done, whatever its directory holds.

The output is a path or a URI (s3://, gs://, ...) opened with `pyarrow.fs.FileSystem.from_uri`;
a local path goes through the same calls as a bucket, so the tests of local campaigns exercise
the code that writes to remote ones.
"""

from __future__ import annotations

import json
import os
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow.fs as pafs

from companion.core.files import dump_json

__all__ = ["CampaignOutput", "output_uri"]

SPEC_FILE = "campaign.spec.json"
"""The flights the directory was made for: a second run with another specification is refused."""


def output_uri(where: str | Path) -> str:
    """A campaign output as a URI or an absolute local path (pyarrow refuses relative ones)."""
    text = str(where)
    if "://" in text:
        return text
    return str(Path(text).expanduser().resolve())


@dataclass(frozen=True)
class CampaignOutput:
    """The campaign's output directory on whatever file system holds it."""

    uri: str

    @property
    def fs_and_base(self) -> tuple[pafs.FileSystem, str]:
        fs, base = pafs.FileSystem.from_uri(self.uri)
        return fs, base.rstrip("/")

    @property
    def local_dir(self) -> Path | None:
        """The directory itself when it is on this machine's file system, else None."""
        fs, base = self.fs_and_base
        return Path(base) if isinstance(fs, pafs.LocalFileSystem) else None

    def path(self, *parts: str) -> str:
        return "/".join([self.fs_and_base[1], *parts])

    def write_text(self, rel: str, text: str) -> None:
        """Replace `rel` atomically: a temporary name beside it, then a rename (and fsync on a
        local disk), so a reader sees the old text or the new, never half of one."""
        fs, _ = self.fs_and_base
        target = self.path(rel)
        parent = target.rsplit("/", 1)[0]
        fs.create_dir(parent, recursive=True)
        tmp = f"{parent}/.{target.rsplit('/', 1)[1]}.{uuid.uuid4().hex}.tmp"
        try:
            with fs.open_output_stream(tmp) as out:
                out.write(text.encode("utf-8"))
            if isinstance(fs, pafs.LocalFileSystem):
                fd = os.open(tmp, os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
            fs.move(tmp, target)
        except BaseException:
            try:
                fs.delete_file(tmp)
            except OSError:
                pass
            raise

    def read_json(self, rel: str) -> dict[str, Any] | None:
        fs, _ = self.fs_and_base
        try:
            with fs.open_input_stream(self.path(rel)) as src:
                data = json.loads(src.read().decode("utf-8"))
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            return None  # a marker that cannot be read is no marker: the flight is flown again
        return data if isinstance(data, dict) else None

    def exists(self, rel: str) -> bool:
        fs, _ = self.fs_and_base
        return fs.get_file_info(self.path(rel)).type != pafs.FileType.NotFound

    def remove_dir(self, rel: str) -> None:
        fs, _ = self.fs_and_base
        if self.exists(rel):
            fs.delete_dir(self.path(rel))

    # the state proper ---------------------------------------------------------------------

    def marker(self, name: str) -> dict[str, Any] | None:
        """A flight's completion record, when it has one."""
        return self.read_json(f"runs/{name}.json")

    def write_marker(self, name: str, record: dict[str, Any]) -> None:
        self.write_text(f"runs/{name}.json", dump_json(record) + "\n")

    def claim(self, flights: list[dict[str, Any]], what: str) -> None:
        """Record which flights this directory is for, or refuse a directory made for others
        (resuming a campaign with a changed specification would mix two campaigns)."""
        wanted = {"flights": flights}
        have = self.read_json(SPEC_FILE)
        if have is None:
            self.write_text(SPEC_FILE, dump_json(wanted) + "\n")
        elif json.loads(dump_json(have)) != json.loads(dump_json(wanted)):
            raise ValueError(f"{self.uri} holds another campaign ({SPEC_FILE} lists other "
                             f"flights than {what}): give a new --campaign-dir")
