"""The contact stage's rings of neighbours (corner_rings): one sort of the corner edges gives
each element the neighbours, in the order, that a pass over every edge per element gives."""

from __future__ import annotations

import numpy as np
from cellbridge.daemon.core.contacts import corner_rings
from cellbridge.tactile import SkinLayout, grid_layout
from hypothesis import given, settings
from hypothesis import strategies as st


def plain_rings(layout: SkinLayout) -> list[np.ndarray]:
    """The plain path: for every element, two passes over every corner edge."""
    e = layout.corner_edges
    return [np.concatenate([e[e[:, 0] == i, 1], e[e[:, 1] == i, 0]]) for i in range(layout.n)]


def assert_same(layout: SkinLayout) -> None:
    got, want = corner_rings(layout), plain_rings(layout)
    assert len(got) == len(want) == layout.n
    for g, w in zip(got, want):
        assert g.dtype == np.int64
        assert g.tolist() == w.tolist()  # the same neighbours, in the same order


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_rings_equal_the_plain_pass_on_any_layout(data: st.DataObject) -> None:
    """Elements on a grid's cells with holes, in any order (the edges then come in any
    order, and a row's neighbours from both ends of its edges), lone elements included."""
    rows, cols = data.draw(st.integers(1, 7)), data.draw(st.integers(1, 7))
    cells = data.draw(st.lists(st.integers(0, rows * cols - 1), min_size=1, max_size=rows * cols, unique=True))
    side = 0.04
    pitch = side * data.draw(st.sampled_from([1.0, 1.1, 2.5]))  # touching, a seam, apart (no neighbours)
    centres = np.array([[(c % cols) * pitch, (c // cols) * pitch] for c in cells])
    assert_same(SkinLayout(centres, side=side))


def test_rings_on_a_grid_name_every_neighbour_corners_included() -> None:
    lay = grid_layout(3, 3)
    rings = corner_rings(lay)
    assert sorted(rings[4].tolist()) == [0, 1, 2, 3, 5, 6, 7, 8]  # the centre: all eight
    assert sorted(rings[0].tolist()) == [1, 3, 4]
    assert_same(lay)
