"""A frame whose every reading is known: ContactStage.run gives each contact what
bound_by_unknown gives it (``unknown_near`` empty, nothing widened) without asking it per
contact."""

from __future__ import annotations

import numpy as np
from cellbridge.daemon.core.contacts import ContactStage, EstimateRequest, bound_by_unknown
from cellbridge.daemon.core.elements import default_params
from cellbridge.tactile.layout import grid_layout
from cellbridge.tactile.response import skin_response
from hypothesis import given, settings
from hypothesis import strategies as st


@settings(max_examples=30)
@given(st.lists(st.tuples(st.floats(0.0, 0.2), st.floats(0.0, 0.2), st.floats(0.3, 6.0), st.floats(0.006, 0.03)),
                min_size=1, max_size=3), st.integers(0, 2**32 - 1), st.booleans())
def test_contacts_of_a_frame_all_known_are_bound_by_unknown_s(press, seed, flags):
    lay = grid_layout(6, 6)
    disks: list[tuple[float, float, float, float]] = []
    for x, y, f, d in press:
        if all(np.hypot(x - u, y - v) > 0.5 * (d + e) for u, v, _, e in disks):
            disks.append((x, y, f, d))
    dc1, dc2 = skin_response(lay, disks)
    dc = np.stack([dc1, dc2], axis=1) + np.random.default_rng(seed).normal(0.0, 2e-15, (lay.n, 2))
    touched: np.ndarray = np.asarray((dc > 50e-15).any(axis=1), dtype=bool)
    stage = ContactStage(lay, default_params(lay), 2e-15, "capacitance", birth_frames=1)
    unknown = np.zeros(lay.n, dtype=bool) if flags else None  # (all known, said either way)
    got = []
    for k in range(2):
        got += stage.run(EstimateRequest("t", b"", None, dc, touched, 0.01 * k, 0.01 * k, unknown, 0, ()))
    for c in got:
        plain = {k: v for k, v in c.items() if k != "unknown_near"}
        assert bound_by_unknown(plain, lay, stage._row, stage._ring, np.zeros(lay.n, dtype=bool)) == c
