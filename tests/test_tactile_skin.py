"""Skin array: layout, exact disk–rectangle overlap, array response (cellbridge.tactile.layout, .overlap, .response)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from cellbridge.tactile.element import ElementParams, forward, sensitivity
from cellbridge.tactile.layout import SkinLayout, grid_layout, layout_from_mapping, layout_to_toml, parse_layout
from cellbridge.tactile.overlap import disk_element_overlap, disk_rect_overlap
from cellbridge.tactile.response import _disk_blur, disk_response, pressure_field, skin_response
from hypothesis import given, settings
from hypothesis import strategies as st

from cellbridge.config import load_layout

# ----------------------------------------------------------------- reference areas


def chord_integral(cx, cy, r, x0, y0, x1, y1, n=20000):
    """Area by integrating, over x, the length of the vertical chord inside the rectangle.

    Independent of the closed form: a midpoint rule on a 1-D integrand that is
    continuous, so the error is O(h^1.5) at worst (at tangencies).
    """
    h = (x1 - x0) / n
    x = x0 + (np.arange(n) + 0.5) * h
    half = np.sqrt(np.maximum(r * r - (x - cx) ** 2, 0.0))
    length = np.maximum(np.minimum(y1, cy + half) - np.maximum(y0, cy - half), 0.0)
    return float(length.sum() * h)


def monte_carlo(cx, cy, r, x0, y0, x1, y1, n=400_000, seed=0):
    rng = np.random.default_rng(seed)
    px = rng.uniform(x0, x1, n)
    py = rng.uniform(y0, y1, n)
    frac = np.mean((px - cx) ** 2 + (py - cy) ** 2 <= r * r)
    area = (x1 - x0) * (y1 - y0)
    return frac * area, math.sqrt(frac * (1 - frac) / n) * area


coord = st.floats(-2.0, 2.0, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(coord, coord, st.floats(1e-3, 2.0), coord, coord, coord, coord)
def test_overlap_matches_chord_integral(cx, cy, r, a, b, c, d):
    x0, x1 = sorted((a, b))
    y0, y1 = sorted((c, d))
    exact = float(disk_rect_overlap(cx, cy, r, x0, y0, x1, y1))
    ref = chord_integral(cx, cy, r, x0, y0, x1, y1)
    assert exact == pytest.approx(ref, abs=2e-6 + 1e-6 * r * r)
    assert 0.0 <= exact <= min(math.pi * r * r, (x1 - x0) * (y1 - y0)) * (1 + 1e-12)


@pytest.mark.parametrize(
    "case",
    [
        (0.3, -0.2, 0.7, -0.5, -0.5, 0.5, 0.5),
        (0.0, 0.0, 1.0, 0.2, 0.3, 3.0, 3.0),
        (1.0, 1.0, 0.5, 0.0, 0.0, 1.2, 5.0),
        (-0.4, 0.1, 0.9, -1.0, -0.2, 0.1, 0.4),
    ],
)
def test_overlap_matches_monte_carlo(case):
    exact = float(disk_rect_overlap(*case))
    mc, sd = monte_carlo(*case)
    assert abs(exact - mc) <= 5 * sd + 1e-12


def test_overlap_special_cases():
    r = 0.013
    assert disk_rect_overlap(0, 0, r, -1, -1, 1, 1) == pytest.approx(math.pi * r * r, rel=1e-14)
    assert disk_rect_overlap(5, 5, r, -1, -1, 1, 1) == 0.0
    # Half-plane, quadrant, and a tangent rectangle.
    assert disk_rect_overlap(0, 0, r, 0, -1, 1, 1) == pytest.approx(math.pi * r * r / 2, rel=1e-13)
    assert disk_rect_overlap(0, 0, r, 0, 0, 1, 1) == pytest.approx(math.pi * r * r / 4, rel=1e-13)
    assert disk_rect_overlap(0, 0, r, r, -1, 1, 1) == pytest.approx(0.0, abs=1e-20)
    # Rectangle inside the disk: its own area.
    assert disk_rect_overlap(0, 0, r, -0.003, -0.004, 0.005, 0.002) == pytest.approx(0.008 * 0.006, rel=1e-12)
    # Circular segment of height h: r²·acos(1−h/r) − (r−h)·√(2rh−h²).
    h = 0.004
    seg = r * r * math.acos(1 - h / r) - (r - h) * math.sqrt(2 * r * h - h * h)
    assert disk_rect_overlap(0, 0, r, r - h, -1, 1, 1) == pytest.approx(seg, rel=1e-12)
    # Radius zero and degenerate rectangles.
    assert disk_rect_overlap(0, 0, 0.0, -1, -1, 1, 1) == 0.0
    assert disk_rect_overlap(0, 0, r, 0, 0, 0, 1) == 0.0


@settings(max_examples=60, deadline=None)
@given(st.floats(-0.05, 0.05), st.floats(-0.05, 0.05), st.floats(1e-4, 0.05))
def test_overlap_partition_sums_to_disk(cx, cy, r):
    # Rectangles tiling a region that contains the disk share out exactly its area.
    edges = np.linspace(-0.2, 0.2, 9)
    x0, y0 = np.meshgrid(edges[:-1], edges[:-1])
    x1, y1 = np.meshgrid(edges[1:], edges[1:])
    tot = disk_rect_overlap(cx, cy, r, x0, y0, x1, y1).sum()
    assert tot == pytest.approx(math.pi * r * r, rel=1e-11)


def test_overlap_broadcasts_and_scales():
    rng = np.random.default_rng(3)
    c = rng.uniform(-1, 1, (7, 2))
    r = rng.uniform(0.1, 1, 7)
    b = np.array([[-1, -1, 0, 0.5], [0, -0.5, 1, 1], [-0.3, -0.3, 0.3, 0.3]])
    a = disk_rect_overlap(c[:, :1], c[:, 1:], r[:, None], b[:, 0], b[:, 1], b[:, 2], b[:, 3])
    assert a.shape == (7, 3)
    for i in range(7):
        for j in range(3):
            assert a[i, j] == disk_rect_overlap(c[i, 0], c[i, 1], r[i], *b[j])
    k = 0.04
    a2 = disk_rect_overlap(k * c[:, :1], k * c[:, 1:], k * r[:, None], *(k * b.T))
    np.testing.assert_allclose(a2, k * k * a, rtol=1e-12, atol=1e-18)


def test_overlap_rejects_bad_input():
    with pytest.raises(ValueError):
        disk_rect_overlap(0, 0, -1.0, 0, 0, 1, 1)
    with pytest.raises(ValueError):
        disk_rect_overlap(0, 0, np.nan, 0, 0, 1, 1)
    with pytest.raises(ValueError):
        disk_rect_overlap(0, 0, 1.0, 1, 0, 0, 1)


# --------------------------------------------------------------------------- layout


def test_grid_layout_geometry_and_neighbours():
    lay = grid_layout(2, 3, pitch=0.04, first_id=10)
    assert lay.n == 6 and list(lay.ids) == [10, 11, 12, 13, 14, 15]
    np.testing.assert_allclose(lay.centres[4], [0.04, 0.04])
    np.testing.assert_allclose(lay.bounds[0], [-0.02, -0.02, 0.02, 0.02])
    assert {tuple(e) for e in lay.edges} == {(0, 1), (1, 2), (3, 4), (4, 5), (0, 3), (1, 4), (2, 5)}
    assert len(lay.corner_edges) == 7 + 4
    adj = lay.adjacency()
    assert (adj == adj.T).all() and not adj.diagonal().any()
    assert list(lay.neighbours(1)) == [0, 2, 4]
    assert list(lay.index_of([15, 10])) == [5, 0]
    with pytest.raises(ValueError):
        lay.index_of([99])
    assert list(lay.element_at([[0.0, 0.0], [0.05, 0.03], [1.0, 1.0]])) == [0, 4, -1]
    assert lay.extent == pytest.approx((-0.02, -0.02, 0.10, 0.06))


def test_neighbours_across_seams():
    near = grid_layout(1, 2, pitch=0.044, side=0.040)  # 4 mm seam
    assert len(near.edges) == 1
    far = grid_layout(1, 2, pitch=0.060, side=0.040)  # 20 mm: no contact bridges it
    assert len(far.edges) == 0
    tight = SkinLayout(near.centres, 0.040, neighbour_gap=0.001)
    assert len(tight.edges) == 0


def test_layout_validation():
    with pytest.raises(ValueError, match="overlap"):
        SkinLayout(np.array([[0.0, 0.0], [0.03, 0.0]]), side=0.04)
    with pytest.raises(ValueError, match="unique"):
        SkinLayout(np.array([[0.0, 0.0], [0.04, 0.0]]), ids=np.array([1, 1]))
    with pytest.raises(ValueError):
        SkinLayout(np.zeros((2, 3)))
    with pytest.raises(ValueError):
        SkinLayout(np.array([[0.0, np.nan]]))
    with pytest.raises(ValueError):
        SkinLayout(np.array([[0.0, 0.0]]), side=-1)
    with pytest.raises(ValueError):
        grid_layout(2, 2, pitch=0.03, side=0.04)
    with pytest.raises(ValueError):
        grid_layout(0, 2)


def test_layout_files(tmp_path):
    p = tmp_path / "grid.toml"
    p.write_text("[grid]\nrows = 2\ncols = 2\npitch = 0.04\norigin = [0.1, 0.2]\nfirst_id = 5\n")
    lay = load_layout(p)
    assert list(lay.ids) == [5, 6, 7, 8]
    np.testing.assert_allclose(lay.centres[3], [0.14, 0.24])

    free = tmp_path / "free.toml"
    free.write_text(
        "side = 0.04\n\n[[element]]\nid = 3\nx = 0.0\ny = 0.0\n\n[[element]]\nid = 9\nx = 0.04\ny = 0.0\n"
    )
    lay2 = load_layout(free)
    assert list(lay2.ids) == [3, 9] and len(lay2.edges) == 1

    rt = tmp_path / "rt.toml"
    rt.write_text(layout_to_toml(lay))
    lay3 = load_layout(rt)
    np.testing.assert_array_equal(lay3.centres, lay.centres)
    np.testing.assert_array_equal(lay3.ids, lay.ids)

    bad = tmp_path / "bad.toml"
    for text in ("[grid\n", "[grid]\nrows = 2\n", "side = 1\n", "[grid]\nrows=1\ncols=1\nfoo=2\n",
                 "[[element]]\nid = 1\nx = 0\n", "[[element]]\nid = 1.5\nx = 0\ny = 0\n"):
        bad.write_text(text)
        with pytest.raises(ValueError):
            load_layout(bad)
    with pytest.raises(ValueError, match="my-skin"):
        parse_layout("[grid\n", source="my-skin")
    with pytest.raises(ValueError):
        load_layout(tmp_path / "missing.toml")
    with pytest.raises(ValueError):
        layout_from_mapping({"grid": {"rows": 1, "cols": 1}, "element": []})


# ------------------------------------------------------------------------- response

LAY = grid_layout(2, 2)
P = ElementParams()


def test_disk_inside_one_element_reproduces_forward():
    for f, d in [(0.5, 0.010), (3.0, 0.010), (3.0, 0.026), (10.0, 0.040)]:
        d1, d2 = skin_response(LAY, [0.0, 0.0, f, d])
        e1, e2 = forward(f, math.pi * d * d / 4)
        assert d1[0] == pytest.approx(float(e1), rel=1e-12)
        assert d2[0] == pytest.approx(float(e2), rel=1e-12)
        assert np.all(d1[1:] == 0) and np.all(d2[1:] == 0)


def test_straddling_contact_splits_by_overlap_at_one_pressure():
    x, y, f, d = 0.018, 0.023, 4.0, 0.016
    d1, d2 = skin_response(LAY, [x, y, f, d])
    s = math.pi * d * d / 4
    g1, g2 = sensitivity(f / s)
    a = disk_element_overlap(LAY, [[x, y]], [d / 2])[0]
    assert np.all(a > 0) and a.sum() == pytest.approx(s, rel=1e-12)
    np.testing.assert_allclose(d1, a * g1, rtol=1e-12)
    np.testing.assert_allclose(d2, a * g2, rtol=1e-12)
    # Every piece has the ratio of the whole contact: the inverse sees one pressure.
    np.testing.assert_allclose(d1 / d2, float(g1 / g2), rtol=1e-12)


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(-0.02, 0.06), st.floats(-0.02, 0.06), st.floats(0.0, 10.0), st.floats(0.002, 0.02)),
        min_size=1,
        max_size=4,
    )
)
def test_contributions_add(contacts):
    c = np.array(contacts)
    # Keep the disks apart (the model's assumption): drop any that overlaps an earlier one.
    keep: list[int] = []
    for i in range(len(c)):
        if all(np.hypot(*(c[i, :2] - c[j, :2])) > (c[i, 3] + c[j, 3]) / 2 for j in keep):
            keep.append(i)
    c = c[keep]
    d1, d2 = skin_response(LAY, c)
    s1 = sum(skin_response(LAY, row)[0] for row in c)
    s2 = sum(skin_response(LAY, row)[1] for row in c)
    np.testing.assert_allclose(d1, s1, rtol=1e-12, atol=1e-30)
    np.testing.assert_allclose(d2, s2, rtol=1e-12, atol=1e-30)
    per = disk_response(LAY, c)
    np.testing.assert_allclose(per[0].sum(axis=0), d1, rtol=1e-12, atol=1e-30)


def test_response_edge_cases_and_errors():
    z1, z2 = skin_response(LAY, [])
    assert z1.shape == (4,) and not z1.any() and not z2.any()
    assert not skin_response(LAY, [0.5, 0.5, 3.0, 0.01])[0].any()  # off the skin
    assert not skin_response(LAY, [0.0, 0.0, 0.0, 0.01])[0].any()  # no force
    for bad in ([0, 0, -1.0, 0.01], [0, 0, 1.0, 0.0], [0, 0, np.nan, 0.01], [[0, 0, 1.0]]):
        with pytest.raises(ValueError):
            skin_response(LAY, bad)
    with pytest.raises(ValueError):
        skin_response(LAY, [0, 0, 1.0, 0.01], spread=-1e-3)


# --------------------------------------------------------------------------- spread


def test_disk_blur_matches_brute_force_convolution():
    r, s, h = 0.005, 0.001, 4e-5
    xs = np.arange(-0.012, 0.012, h) + h / 2
    X, Y = np.meshgrid(xs, xs)
    inside = (X**2 + Y**2 <= r * r).astype(float)
    for rho in (0.0, 0.003, 0.005, 0.0065):
        g = np.exp(-((X - rho) ** 2 + Y**2) / (2 * s * s)) / (2 * math.pi * s * s)
        brute = (inside * g).sum() * h * h
        assert float(_disk_blur(np.array([rho]), np.array([r]), s)[0]) == pytest.approx(brute, abs=2e-3)
    # Far inside a large disk the blur changes nothing; far outside it is nothing.
    assert float(_disk_blur(np.array([0.0]), np.array([0.05]), s)[0]) == pytest.approx(1.0, abs=1e-12)
    assert float(_disk_blur(np.array([0.02]), np.array([0.005]), s)[0]) == 0.0


def test_spread_conserves_force():
    pts = np.stack(np.meshgrid(np.arange(-0.03, 0.03, 2e-4), np.arange(-0.03, 0.03, 2e-4)), -1)
    f = pressure_field(pts, [0.0, 0.0, 3.0, 0.01], spread=0.002).sum() * 2e-4**2
    assert f == pytest.approx(3.0, rel=1e-4)


def test_spread_is_linear_limit_preserving_and_symmetric():
    # At very low pressure the foams are linear, so blurring (which keeps the force)
    # leaves an element's total ΔC unchanged as long as the blur stays on it.
    big = grid_layout(1, 1, pitch=0.2)
    c = [0.0, 0.0, 1e-5, 0.010]
    a1, a2 = skin_response(big, c)
    b1, b2 = skin_response(big, c, spread=0.002)
    assert b1[0] == pytest.approx(a1[0], rel=2e-4)
    assert b2[0] == pytest.approx(a2[0], rel=2e-4)
    # A contact centred on a seam loads both sides equally.
    s1, s2 = skin_response(LAY, [0.02, 0.0, 3.0, 0.01], spread=0.002)
    assert s1[0] == pytest.approx(s1[1], rel=1e-6) and s2[0] == pytest.approx(s2[1], rel=1e-6)
    # And the blur reaches an element the disk itself does not touch.
    t1, _ = skin_response(LAY, [0.0135, 0.0, 3.0, 0.01], spread=0.002)
    assert t1[1] > 0 and skin_response(LAY, [0.0135, 0.0, 3.0, 0.01])[0][1] == 0


def test_spread_converges_to_uniform_model():
    c = [0.018, 0.0, 3.0, 0.010]
    u1, _ = skin_response(LAY, c)
    dev = [np.abs(skin_response(LAY, c, spread=s)[0] - u1).max() for s in (0.002, 0.001, 0.0005)]
    # First order in s: the rim band where pressure is blurred has width ∝ s.
    assert 0.4 < dev[1] / dev[0] < 0.6 and 0.4 < dev[2] / dev[1] < 0.6


# ------------------------------------------------- issue 9: layout files, neighbours


GRID = "[grid]\nrows = 2\ncols = 2\n"


@pytest.mark.parametrize(
    "text, key",
    [
        ("side = true\n" + GRID, "side"),
        ('side = "0.04"\n' + GRID, "side"),
        ("side = nan\n" + GRID, "side"),
        ("neighbour_gap = true\n" + GRID, "neighbour_gap"),
        ("[grid]\nrows = inf\ncols = 2\n", "rows"),
        ("[grid]\nrows = 2.0\ncols = 2\n", "rows"),
        ("[grid]\nrows = true\ncols = 2\n", "rows"),
        ("[grid]\nrows = -1\ncols = 2\n", "rows"),
        ("[grid]\nrows = 2\ncols = 2\nfirst_id = 1.7\n", "first_id"),
        ('[grid]\nrows = 2\ncols = 2\npitch = "0.04"\n', "pitch"),
        ("[grid]\nrows = 2\ncols = 2\npitch = inf\n", "pitch"),
        ('[grid]\nrows = 2\ncols = 2\norigin = ["0", 0.0]\n', "origin"),
        ("[grid]\nrows = 2\ncols = 2\norigin = [0.0]\n", "origin"),
        ("grid = 3\n", "grid"),
        ('[[element]]\nid = 1\nx = "0.04"\ny = 0.0\n', "x"),
        ("[[element]]\nid = 1\nx = 0.0\ny = true\n", "y"),
        ("[[element]]\nid = true\nx = 0.0\ny = 0.0\n", "id"),
        ("[[element]]\nid = 1\nx = 0.0\ny = 0.0\n[[element]]\nid = 2\nx = 0.0\ny = 0.0\n", "overlap"),
        ("[[element]]\nid = 1\nx = 0.0\n", "y"),
    ],
)
def test_layout_files_reject_wrong_types_naming_file_and_key(text, key):
    _refused_naming(text, key)


def _refused_naming(text: str, key: str) -> None:
    """The layout file ``text`` is refused with a ValueError naming the file and ``key``."""
    with pytest.raises(ValueError) as info:
        parse_layout(text, source="arm.toml")
    msg = str(info.value)
    assert msg.startswith("arm.toml: ") and key in msg, msg


def test_grid_layout_checks_its_arguments():
    cases: list[tuple[dict[str, Any], str]] = [({"rows": math.inf}, "rows"), ({"rows": True}, "rows"),
                        ({"first_id": 1.7}, "first_id"), ({"pitch": "0.04"}, "pitch"),
                        ({"origin": (0.0, math.nan)}, "origin"), ({"side": math.inf}, "side")]
    for kwargs, key in cases:
        args = {"rows": 2, "cols": 2} | kwargs
        with pytest.raises(ValueError, match=key):
            grid_layout(**args)
    assert list(grid_layout(np.int64(1), 2, first_id=np.int32(4)).ids) == [4, 5]  # type: ignore[arg-type]  # numpy integers, on purpose
    assert grid_layout(1, 2, pitch=1).side == 1.0  # an integer is a number of metres


def brute_force_edges(lay, connectivity):
    b = lay.bounds
    gx = np.maximum(b[None, :, 0] - b[:, None, 2], b[:, None, 0] - b[None, :, 2])
    gy = np.maximum(b[None, :, 1] - b[:, None, 3], b[:, None, 1] - b[None, :, 3])
    close_x, close_y = gx <= lay.neighbour_gap, gy <= lay.neighbour_gap
    share = 1e-6 * lay.side
    if connectivity == "edge":
        adj = (close_x & (gy < -share)) | (close_y & (gx < -share))
    else:
        adj = close_x & close_y
    i, j = np.nonzero(np.triu(adj, 1))
    return np.stack([i, j], axis=1)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.0, 0.03))
def test_neighbours_match_all_pairs_on_irregular_layouts(seed, gap):
    # Jittered grid with holes, seams of random width: the spatial index finds
    # exactly the pairs an all-pairs comparison finds, in the same order.
    rng = np.random.default_rng(seed)
    r, c = np.meshgrid(np.arange(9), np.arange(11), indexing="ij")
    centres = np.stack([c.ravel(), r.ravel()], axis=1) * 0.05 + rng.uniform(-0.004, 0.004, (99, 2))
    keep = rng.random(99) < 0.8
    lay = SkinLayout(centres[keep], side=0.04, neighbour_gap=gap)
    np.testing.assert_array_equal(lay.edges, brute_force_edges(lay, "edge"))
    np.testing.assert_array_equal(lay.corner_edges, brute_force_edges(lay, "corner"))


def test_neighbour_search_is_local():
    # The candidate pairs grow with N, not N²: a 60×60 grid examines at most the
    # 3×3 cells around each element (O(N²) took 44 s for 30 000 elements).
    lay = grid_layout(60, 60)
    pairs = lay._near_pairs
    assert pairs.shape[0] <= 9 * lay.n
    assert len(lay.edges) == 2 * 60 * 59 and len(lay.corner_edges) == 2 * 60 * 59 + 2 * 59 * 59
    with pytest.raises(ValueError, match="overlap"):
        SkinLayout(np.concatenate([lay.centres, [[1.0, 1.0 + 1e-3]]]), side=0.04)


# ------------------------------------------------------------- hostile layout files


@pytest.mark.parametrize(
    "text, key",
    [
        ("[[element]]\nid = 9223372036854775808\nx = 0.0\ny = 0.0\n", "id"),
        ("[[element]]\nid = -9223372036854775809\nx = 0.0\ny = 0.0\n", "id"),
        ("[grid]\nrows = 1\ncols = 2\nfirst_id = 9223372036854775808\n", "first_id"),
        ("[grid]\nrows = 1\ncols = 2\nfirst_id = 9223372036854775807\n", "first_id"),  # would wrap
        ("[grid]\nrows = 1000000000\ncols = 1000000000\n", "rows"),
        ("[grid]\nrows = 1000000000000000000000\ncols = 2\n", "rows"),
        ("side = 40.0\n[grid]\nrows = 1\ncols = 1\npitch = 40.0\n", "side"),  # millimetres
        ("neighbour_gap = 1e300\n[grid]\nrows = 2\ncols = 2\n", "neighbour_gap"),
        ("[[element]]\nid = 1\nx = 1e17\ny = 0.0\n[[element]]\nid = 2\nx = 1.0000000000000001e17\ny = 0.0\n",
         "centre"),
        ("[[element]]\nid = 1\nx = -1e300\ny = 0.0\n[[element]]\nid = 2\nx = -1e300\ny = 0.01\n", "centre"),
        ("x = " + "[" * 100_000 + "]" * 100_000 + "\n", "TOML"),
        ("side = " + "{a = " * 5_000 + "1" + "}" * 5_000 + "\n", "TOML"),
    ],
)
def test_hostile_layout_files_are_refused_with_a_value_error_naming_the_key(text, key):
    # Huge ids used to escape as OverflowError or wrap silently into negative ids, a
    # huge grid as MemoryError, deep nesting as RecursionError; coordinates so large
    # that float64 cannot resolve an element's edges let two elements at the same
    # place pass the overlap check.
    _refused_naming(text, key)


def test_layout_ids_outside_int64_are_refused_not_wrapped():
    xy = np.array([[0.0, 0.0], [0.04, 0.0]])
    for ids in (np.array([2**64 - 1, 2**63], dtype=np.uint64), np.array([2.0**63, 0.0]),
                np.array([1e300, 2e300])):
        with pytest.raises(ValueError, match="ids"):
            SkinLayout(xy, ids=ids)  # type: ignore[arg-type]  # ids no int64 holds, on purpose
    assert list(SkinLayout(xy, ids=np.array([2**63 - 1, 0], dtype=np.uint64)).ids) == [2**63 - 1, 0]


def test_index_of_and_neighbours_refuse_what_is_not_an_integer():
    lay = grid_layout(2, 2)
    with pytest.raises(ValueError, match="id"):
        lay.index_of([0.5])  # used to truncate to id 0
    with pytest.raises(ValueError, match="id"):
        lay.index_of([2**70])  # used to raise OverflowError
    with pytest.raises(ValueError, match="index"):
        lay.neighbours(1.5)  # type: ignore[arg-type]  # used to return no neighbours
    assert list(lay.index_of([3.0, np.int32(1)])) == [3, 1]  # type: ignore[arg-type]  # integral float and numpy ids, on purpose
    assert list(lay.neighbours(np.int64(1))) == [0, 3]  # type: ignore[arg-type]  # a numpy integer, on purpose


@pytest.mark.parametrize("r", [1.0, 1e3, 1e5, 1e8, 1e200])
def test_an_element_wholly_inside_a_huge_disk_gets_its_whole_area(r):
    # The closed form is a difference of four O(1) corner terms scaled by r²: for an
    # element far inside a large disk it lost every digit (r = 1e5 m: 0.08 % short,
    # r = 1e8 m: 0). A rectangle whose corners all lie in the disk is exactly inside.
    area = disk_rect_overlap(0.3, -0.2, r, -0.02, -0.02, 0.02, 0.02)
    assert area == 0.04 * 0.04
    lay = grid_layout(2, 2)
    b = lay.bounds
    np.testing.assert_array_equal(disk_element_overlap(lay, [[0.02, 0.02]], [r]),
                                  ((b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]))[None, :])


def test_a_spread_below_a_nanometre_is_refused_not_wrong():
    # spread = 1e-100 m gave all-zero responses (the profile's grid collapsed to one
    # point) and 1e-160 m a NaN pressure error from deep inside the element model.
    lay = grid_layout(2, 2)
    for s in (1e-100, 1e-160, 5e-324):
        with pytest.raises(ValueError, match="spread"):
            skin_response(lay, [[0.005, 0.003, 3.0, 0.01]], spread=s)
    with pytest.raises(ValueError, match="spread"):
        pressure_field([[0.0, 0.0]], [[0.0, 0.0, 3.0, 0.01]], spread=1e-300)
    fine = skin_response(lay, [[0.005, 0.003, 3.0, 0.01]], spread=1e-9)[0]
    flat = skin_response(lay, [[0.005, 0.003, 3.0, 0.01]], spread=0.0)[0]
    np.testing.assert_allclose(fine, flat, rtol=1e-3)
