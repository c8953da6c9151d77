"""The estimator learns a receiver's latency in flight: a lockstep SITL flight whose GPS fixes
arrive a known 0.2 s late, read back from the estimator's own log (``estimator.bin``).

The filter's unit tests (tests/test_estimation_eskf.py) check the delay state on synthetic
data; this is the path a user relies on: the simulated receiver's late NMEA, the GPS driver,
the estimator thread, its log. The simple GPS profile's driver measures no latency of its own
(no PPS), so the whole delay is the filter's to find, starting from its prior (``EST_GPS_LAG``
0.05 s, 1-sigma ``EST_GPS_LAGSD`` 0.1 s).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from test_sim_lockstep import fly

from companion.estimation.logformats import FMT_GPS
from companion.logs import read_log

TRUE_LATENCY_S = 0.2
DURATION_S = 40.0  # simulated; lockstep flies it in 4-10 s of host time on this machine


def test_the_gps_latency_estimate_converges_to_the_receivers_in_a_flight(tmp_path: Path) -> None:
    summary, fdir = fly(tmp_path, DURATION_S, scenario="turns", seed=1,
                        gps_latency_s=TRUE_LATENCY_S)
    est = {t["name"]: t for t in summary["threads"]}["estimator"]
    assert est["restarts"] == 0 and est["crashes"] == 0, est
    fixes = read_log(fdir / "estimator.bin").data(FMT_GPS)
    t_s = fixes["time_s"] - fixes["time_s"][0]
    assert t_s[-1] > DURATION_S - 5.0 and fixes["accepted"].mean() > 0.95
    lag_s, std_s = fixes["latency_s"], fixes["gps_lag_std_s"]
    last = t_s >= t_s[-1] - 5.0
    final_s = float(lag_s[last].mean())
    # Measured over the last 5 s with seeds 1-4: 0.184-0.205 s (1-sigma 0.019 s), from a first
    # fused value near 0.02 s; 0.12 s of truth gave 0.129 s. 0.04 s is twice the filter's
    # own 1-sigma and still far from the prior: a filter that stays put or learns half the
    # delay fails.
    assert abs(final_s - TRUE_LATENCY_S) < 0.04, f"estimate {final_s:.3f} s, truth {TRUE_LATENCY_S}"
    assert abs(float(lag_s[0]) - final_s) > 0.1, "the estimate did not move from its start"
    # ... and the filter knows it has learnt it: its 1-sigma fell from the prior's 0.1 s
    assert float(std_s[last].mean()) < 0.03 and np.all(np.isfinite(lag_s))
