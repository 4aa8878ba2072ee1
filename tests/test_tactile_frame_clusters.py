"""One frame's clusters posed as fit problems (FitRunner.frame_clusters): edge cases."""

from __future__ import annotations

import math

import numpy as np
from cellbridge.tactile.element import ElementParams
from cellbridge.tactile.fit_problems import FitRunner
from cellbridge.tactile.layout import grid_layout


def test_a_valid_element_of_zero_area_gives_no_pressure_not_an_error():
    """Σforce/Σarea of 0/0 is NaN, as numpy's arithmetic gave it: the cluster has no pressure
    (no fit), the frame's other cluster is posed as usual, and nothing raises."""
    lay = grid_layout(4, 4)
    runner = FitRunner(lay, ElementParams(side=lay.side), np.full(2, 1e-15), False)
    labels = np.full(16, -1)
    labels[[0, 1]] = 0
    labels[15] = 1
    c1 = np.full(16, 1e-16)
    c1[[0, 1, 15]] = 2e-13
    valid = np.zeros(16, dtype=bool)
    valid[[0, 1, 15]] = True
    force = np.zeros(16)
    area = np.zeros(16)
    force[15], area[15] = 2.0, 4e-4
    out = runner.frame_clusters(labels, c1, c1 / 2, np.ones(16, dtype=bool), valid, force, area, None, np.full(2, 1e-15))
    assert [cl.members.tolist() for cl in out] == [[0, 1], [15]]
    assert math.isnan(out[0].sigma0) and not out[0].valid
    assert out[1].sigma0 == 2.0 / 4e-4 and out[1].valid
    assert out[1].obs.tolist() == [15, 10, 11, 14]  # the member, then its ring, ascending
