"""The filter's closed-form chi-square gates and white-acceleration process noise agree with
scipy and filterpy (which the flight path no longer imports)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from filterpy.common import Q_continuous_white_noise
from scipy.stats import chi2

from companion.estimation.noise import chi2_cdf_even, chi2_ppf_even, white_accel_q


@pytest.mark.parametrize("dof", [2, 4, 6, 8, 12])
@pytest.mark.parametrize("p", [0.5, 0.9, 0.99, 0.999, 0.9999, 0.999999])
def test_chi2_ppf_matches_scipy(dof: int, p: float) -> None:
    assert chi2_ppf_even(p, dof) == pytest.approx(float(chi2.ppf(p, dof)), rel=1e-10)


@pytest.mark.parametrize("dof", [2, 6])
def test_chi2_cdf_matches_scipy(dof: int) -> None:
    for x in (0.0, 0.1, 1.0, 5.0, 12.6, 40.0):
        assert chi2_cdf_even(x, dof) == pytest.approx(float(chi2.cdf(x, dof)), abs=1e-14)


@pytest.mark.parametrize("bad", [(0.0, 6), (1.0, 6), (0.5, 3), (0.5, 0), (-0.1, 2)])
def test_chi2_ppf_refuses_bad_input(bad: tuple[float, int]) -> None:
    with pytest.raises(ValueError):
        chi2_ppf_even(*bad)


@pytest.mark.parametrize("dt", [0.001, 0.01, 0.02, 0.1, 1.5])
def test_white_accel_q_matches_filterpy(dt: float) -> None:
    ours = white_accel_q(dt, 0.37)
    ref = Q_continuous_white_noise(dim=2, dt=dt, spectral_density=0.37, block_size=3,
                                   order_by_dim=False)
    np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=0.0)


def test_flight_filter_does_not_import_scipy_or_filterpy() -> None:
    code = ("import sys; import companion.estimation.fusion, companion.estimation.thread; "
            "bad = [m for m in ('scipy.stats', 'scipy', 'filterpy') if m in sys.modules]; "
            "print(','.join(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, check=True)
    assert out.stdout.strip() == ""
