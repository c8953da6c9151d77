"""Convert the Leiria robot-arm IMU data set (MATLAB files) into the compact subset in tests/data.

    python bench/make_imu_truth_subset.py SOURCE_DIR [--out tests/data/imu-truth/leiria]

``SOURCE_DIR`` is a checkout of the data set (the folder that holds ``DataSets/``, ``LICENSE``
and ``README.md``). The original ``.mat`` files carry the acquisition scripts' whole workspace
(raw packets, token tables, magnetometer); the tests and the benchmark need only time, gyro,
accelerometer and the robot's orientation, so each recording becomes one small ``.npz``:

* ``t_s`` float64: the PC's MATLAB time of each sample, s, as recorded (not repaired: the
  loader in ``companion/evaluation/realdata.py`` drops non-finite rows and repairs the rare
  non-increasing time stamps, so the file stays faithful to the source);
* ``gyro_rad_s``, ``accel_m_s2`` float32 (N x 3), converted to SI with the per-device unit
  table below (float32 keeps 7 digits, far below the sensors' noise);
* ``truth_wxyz`` float32 (N x 4): ``ABBquaternion``, the robot's tool orientation in its base
  frame, as the acquisition spread it onto the sensor samples;
* ``truth_report_index`` int32: the samples at which robot reports arrived (``TokenPosition``
  minus one, MATLAB counts from 1). The acquisition interpolated the quaternion's
  components linearly between reports without minding their sign, so between two reports that
  straddle a sign change the stored quaternion passes through zero (a spurious half turn); the
  loader re-interpolates from the reports only, with signs made continuous;

* for ``XSENS``: ``t_s``, ``xsens_wxyz`` (the unit's own orientation, ``SENSquat``) and
  ``truth_wxyz`` on the XSENS unit's own samples.

Units (measured on the data: rest norms and gyro-against-robot rates): accelerometers in g for
every device (rest norms 0.996-1.000 g); MPU9150, MPU6500 and MPU6050 gyros in deg/s (clipped
near 450 deg/s, kept as recorded so the filters see the clipping; their rotation increments
match the robot's within 1-2 %). The LSM9DS0 gyro is "about rad/s": its rotation increments are
1.13 times smaller than the robot's (median over 474 half-second windows of all LSM9DS0
recordings, quartiles 1.10 and 1.16), a sensitivity setting that did not match the one used to
scale it, so it is multiplied by 1.13. That calibration is the same for every filter.

``DataSets/V_500/Sequencia2/LSM9DS0.mat`` is byte for byte the same file as
``DataSets/eV50p/Sequencia2/LSM9DS0.mat``; only the eV50p copy is converted.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import shutil
import sys
import warnings
from pathlib import Path

import numpy as np
import scipy.io

G_M_S2 = 9.80665
# device -> gyro unit factor to rad/s (accelerometers are all in g)
GYRO_TO_RAD_S: dict[str, float] = {
    "LSM9DS0": 1.13,
    "MPU9150": math.pi / 180.0,
    "MPU6500RM3100": math.pi / 180.0,
    "MPU6050RM3100": math.pi / 180.0,
}
# eV50p first: of two identical source files the first one met is kept
SPEEDS = ("eV50p", "V_300", "V_500", "V_800", "V1000", "V1500")
PATHS = ("Sequencia1", "Sequencia2", "Sequencia3", "Sequencia4")


def _load(path: Path) -> dict[str, np.ndarray]:
    with warnings.catch_warnings():
        # the acquisition scripts saved a variable named "None" several times; harmless
        warnings.simplefilter("ignore")
        return scipy.io.loadmat(path, squeeze_me=True)  # type: ignore[no-any-return]


def convert_device(src: Path, device: str) -> dict[str, np.ndarray]:
    """One raw-IMU recording in SI units (see the module docstring for the fields)."""
    m = _load(src)
    return {
        "t_s": np.asarray(m["MATLABtime"], dtype=np.float64),
        "gyro_rad_s": (np.asarray(m["SENSgyro"], float).T * GYRO_TO_RAD_S[device]).astype(
            np.float32
        ),
        "accel_m_s2": (np.asarray(m["SENSacc"], float).T * G_M_S2).astype(np.float32),
        "truth_wxyz": np.asarray(m["ABBquaternion"], float).T.astype(np.float32),
        **_reports(m),
    }


def _reports(m: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Report ``i`` of the robot arrived at sample ``TokenPosition[i] - 1`` (MATLAB counts
    from 1); out-of-range and repeated positions are dropped."""
    n = len(np.atleast_1d(m["MATLABtime"]))
    idx = np.asarray(m["TokenPosition"], dtype=np.int64) - 1
    return {"truth_report_index": np.unique(idx[(idx >= 0) & (idx < n)]).astype(np.int32)}


def convert_xsens(src: Path) -> dict[str, np.ndarray]:
    """The XSENS MTi-30's own orientation and the robot's, on the XSENS samples."""
    m = _load(src)
    return {
        "t_s": np.asarray(m["MATLABtime"], dtype=np.float64),
        "xsens_wxyz": np.asarray(m["SENSquat"], float).astype(np.float32),
        "truth_wxyz": np.asarray(m["ABBquaternion"], float).T.astype(np.float32),
        **_reports(m),
    }


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("source", type=Path, help="the data set's folder (holds DataSets/)")
    ap.add_argument("--out", type=Path,
                    default=Path(__file__).resolve().parent.parent
                    / "tests" / "data" / "imu-truth" / "leiria")
    args = ap.parse_args(argv)
    src: Path = args.source
    out: Path = args.out
    if not (src / "DataSets").is_dir():
        print(f"{src} has no DataSets/ folder", file=sys.stderr)
        return 2
    out.mkdir(parents=True, exist_ok=True)
    for name in ("LICENSE", "README.md"):
        shutil.copyfile(src / name, out / name)
    rows = []
    seen: dict[str, str] = {}
    for speed in SPEEDS:
        for path in PATHS:
            folder = src / "DataSets" / speed / path
            if not folder.is_dir():
                continue
            for device in (*GYRO_TO_RAD_S, "XSENS"):
                f = folder / f"{device}.mat"
                if not f.is_file():
                    continue
                digest = hashlib.sha256(f.read_bytes()).hexdigest()
                source = f"DataSets/{speed}/{path}/{device}.mat"
                if digest in seen:
                    rows.append(f"(skipped) {source}: same bytes as {seen[digest]}")
                    continue
                seen[digest] = source
                arrays = convert_xsens(f) if device == "XSENS" else convert_device(f, device)
                dest = out / f"{speed}_{path.replace('Sequencia', 'path')}_{device}.npz"
                np.savez_compressed(dest, **arrays)  # type: ignore[arg-type]
                rows.append(f"{dest.name} <- {source} (sha256 {digest})")
    (out / "FILES.txt").write_text("\n".join(rows) + "\n")
    total = sum(p.stat().st_size for p in out.iterdir())
    converted = sum(1 for r in rows if not r.startswith("(skipped)"))
    print(f"{converted} recordings, {total / 1e6:.2f} MB in {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
