"""``companion horizon detect | stream | synth`` through argparse, on real files and sockets."""

from __future__ import annotations

import argparse
import csv
import io
import socket
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import free_udp_port

from horizon.cli import add_commands


def _run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="companion horizon")
    add_commands(parser.add_subparsers(dest="action", required=True))
    args = parser.parse_args(argv)
    return int(args.func(args))


@pytest.fixture(scope="module")
def synth_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("synth")
    assert _run(["synth", str(out), "--count", "6", "--seed", "3", "--clutter"]) == 0
    return out


def _video(path: Path, n: int = 6) -> None:
    from horizon.synth import SceneSpec, render_scene

    vw = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 10.0, (320, 240))
    for i in range(n):
        img, _ = render_scene(SceneSpec(320, 240, 3.0 * i, 0.1), np.random.default_rng(0))
        vw.write(img)
    vw.release()


def test_detect_folder_to_csv_with_overlays(synth_dir: Path, tmp_path: Path) -> None:
    out_csv = tmp_path / "out.csv"
    rc = _run(["detect", str(synth_dir / "images"), "--csv", str(out_csv), "--overlay", str(tmp_path / "ov")])
    assert rc == 0
    rows = list(csv.DictReader(out_csv.open()))
    truth = {str(synth_dir / r["image"]): r for r in csv.DictReader((synth_dir / "gt.csv").open())}
    assert len(rows) == 6
    for row in rows:
        gt = truth[row["image"]]
        assert row["found"] == "1"
        assert abs(float(row["roll_deg"]) - float(gt["roll_deg"])) < 1.0
        assert abs(float(row["offset_frac"]) - float(gt["offset_frac"])) < 0.02
        assert {"x1", "y1", "x2", "y2", "quality"} <= set(row)
    assert len(list((tmp_path / "ov").glob("*.png"))) == 6


def test_detect_to_stdout_with_baseline(synth_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    first = sorted((synth_dir / "images").iterdir())[0]
    assert _run(["detect", str(first), "--method", "baseline"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert len(rows) == 1 and rows[0]["method"] == "baseline"


def test_detect_video_with_tracking_and_overlay_video(tmp_path: Path) -> None:
    video = tmp_path / "clip.avi"
    _video(video)
    out_csv = tmp_path / "v.csv"
    rc = _run(["detect", str(video), "--csv", str(out_csv), "--overlay-video", str(tmp_path / "ov.avi"),
               "--hfov-deg", "60", "--max-frames", "5"])
    assert rc == 0
    rows = list(csv.DictReader(out_csv.open()))
    assert [r["image"] for r in rows] == ["0", "1", "2", "3", "4"]
    assert all(r["found"] == "1" and r["pitch_deg"] != "" for r in rows)
    assert (tmp_path / "ov.avi").stat().st_size > 0


def test_detect_bad_inputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _run(["detect", str(tmp_path / "nothing.png")]) == 2
    assert "nothing.png: no such file" in capsys.readouterr().err
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    assert _run(["detect", str(bad), "--csv", str(tmp_path / "o.csv")]) == 1
    assert "bad.png" in capsys.readouterr().err
    cam = tmp_path / "cam.json"
    cam.write_text('{"width": 320}')
    assert _run(["detect", str(bad), "--camera", str(cam)]) == 2
    assert "missing field 'height'" in capsys.readouterr().err


def test_stream_video_to_legacy_udp(tmp_path: Path) -> None:
    video = tmp_path / "clip.avi"
    _video(video, 4)
    port = free_udp_port()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx:
        rx.bind(("127.0.0.1", port))
        rx.settimeout(5.0)
        rc = _run(["stream", str(video), "--legacy", f"127.0.0.1:{port}", "--vehicle-id", "9",
                   "--hfov-deg", "60", "--csv", str(tmp_path / "s.csv")])
        assert rc == 0
        datagrams = [rx.recv(2048) for _ in range(4)]
    for i, d in enumerate(datagrams):
        typ, vehicle, size, seq = struct.unpack_from("<BBHI", d)
        assert (typ, vehicle, size, seq) == (0x84, 9, 36, i + 1)
    rolls = [struct.unpack_from("<f", d, 16)[0] for d in datagrams]
    assert np.degrees(rolls) == pytest.approx([0.0, 3.0, 6.0, 9.0], abs=0.5)
    assert len(list(csv.DictReader((tmp_path / "s.csv").open()))) == 4


def test_stream_refuses_what_it_cannot_do(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    video = tmp_path / "clip.avi"
    _video(video, 1)
    assert _run(["stream", str(video), "--legacy", "127.0.0.1:5500"]) == 2
    assert "pitch needs the camera" in capsys.readouterr().err
    assert _run(["stream", str(video), "--hfov-deg", "60"]) == 2
    assert "nothing to send to" in capsys.readouterr().err
    assert _run(["stream", str(video), "--hfov-deg", "60", "--legacy", "127.0.0.1:99999"]) == 2
    assert "port in 1..65535" in capsys.readouterr().err
    assert _run(["stream", str(tmp_path), "--hfov-deg", "60", "--legacy", "127.0.0.1"]) == 2


def test_synth_rejects_unknown_disturbance(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _run(["synth", str(tmp_path), "--disturbance", "fog"]) == 2
    assert "unknown disturbance" in capsys.readouterr().err


def test_hooked_into_the_companion_cli(synth_dir: Path, tmp_path: Path) -> None:
    from companion import cli  # the project's own command: a failed import is a failure
    first = sorted((synth_dir / "images").iterdir())[0]
    out_csv = tmp_path / "c.csv"
    assert cli.main(["horizon", "detect", str(first), "--csv", str(out_csv)]) == 0
    assert len(list(csv.DictReader(out_csv.open()))) == 1
