"""A contact's ``observable`` agrees with its σ: an axis the readings do not pin is never
called observable. A fit whose covariance failed to solve leaves σ infinite on an axis the
kernel did not find flat; the published contact must then say the axis is open."""

from __future__ import annotations

import math

import numpy as np
import pytest
from cellbridge.tactile.fit_problems import Cluster, Fits


def _one_fit(sig_x: float, sig_y: float, flat_x: bool = False, flat_y: bool = False) -> Fits:
    cov = np.diag([sig_x ** 2 if math.isfinite(sig_x) else np.nan,
                   sig_y ** 2 if math.isfinite(sig_y) else np.nan, 0.01, 0.0025])[None]
    return Fits(theta=np.array([[0.057, 0.040, math.log(0.012), math.log(3.0)]]),
                sig=np.array([[sig_x, sig_y, 0.1, 0.05]]),
                flat=np.array([[flat_x, flat_y, False, False]]), cov=cov,
                chi2=np.array([4.0]), cost=np.array([4.0]), ok=np.array([True]))


def _cluster() -> Cluster:
    base = dict(area=1e-4, centroid_x=0.056, centroid_y=0.041, elements=(5, 6), pressure=2.6e4,
                force_sum=2.9)
    return Cluster(members=np.array([0, 1]), obs=np.array([0, 1]), sigma0=2.6e4, area=np.array([5e-5, 5e-5]),
                   y=np.zeros((2, 2)), centroid=(0.056, 0.041), valid=True, base=base)


@pytest.mark.parametrize(("sig", "flat", "seen"), [
    ((2e-4, math.inf), (False, False), (True, False)),
    ((math.inf, 3e-4), (False, False), (False, True)),
    ((math.inf, math.inf), (False, False), (False, False)),
    ((2e-4, 3e-4), (False, False), (True, True)),
    ((2e-4, 5e-3), (False, True), (True, False)),
])
def test_an_axis_with_an_infinite_sigma_is_not_observable(sig: tuple[float, float], flat: tuple[bool, bool],
                                                          seen: tuple[bool, bool]) -> None:
    c = _one_fit(*sig, *flat).contact(_cluster(), 0, dof=3)
    assert c.observable == seen
    for a, s in enumerate((c.sigma_x, c.sigma_y)):
        assert c.observable[a] == (math.isfinite(s) and not flat[a])
