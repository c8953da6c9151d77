"""Replay a PX4 ULog, an ArduPilot DataFlash log or a MAVLink telemetry log through the
on-board estimator.

`companion estimation replay LOG...` (docs/estimation.md, "Replaying PX4 and ArduPilot logs"):
the log's IMU and GPS samples go through the same `EstimatorCore` as the estimator thread (or
an IMU-only filter of `companion.estimation.imu_filters`, VQF unless told, when the log has no
usable GPS or the ESKF cannot start), and the result is written beside the flight controller's
own attitude with the differences summarised.

Modules: `sources` recognises a log and hands it to its reader (`dataflash` with `dfwalk`,
`ulog`, `tlog`), which read it into one small interface (`series.FlightLog`), `runner` cleans the
timelines and compares, `start` and `filters` start and run the estimators, `output` writes the
log, the summary and the figure, `batch` finds many logs and writes their table, `cli` is the
command. Nothing heavy is imported here, so registering the command costs nothing.
"""

from __future__ import annotations
