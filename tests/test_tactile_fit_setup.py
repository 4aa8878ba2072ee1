"""A frame's fit set-up taken in one pass over its clusters gives what a cluster at a time gave.

The estimator poses its fits from the frame's clusters: each one's share-based start
(:meth:`FitRunner.starts`), the hints that may start it (``ContactEstimator._hints_in``) and
whether its quiet ring reads the disk (:attr:`Cluster.ring_reads`, kept once computed). Each
is computed over the clusters' flat arrays, or kept; the plain forms (a cluster at a time,
as they were written first) are the reference here, on random presses, readings and hints.
"""

from __future__ import annotations

import math

import numpy as np
from cellbridge.tactile import ContactEstimator, grid_layout, skin_response
from cellbridge.tactile.element import ElementParams
from cellbridge.tactile.fit_problems import Cluster, FitRunner
from hypothesis import given
from hypothesis import strategies as st


def _plain_starts(runner: FitRunner, clusters: list[Cluster]) -> np.ndarray:
    """starts() of the clusters as a cluster at a time gives it (its ``areas`` path)."""
    return runner.starts(clusters, [cl.area[cl.seen] for cl in clusters])


def _plain_hints_in(est: ContactEstimator, clusters: list[Cluster], hints: np.ndarray,
                    d_start: np.ndarray) -> list[np.ndarray]:
    """The hints of each cluster, as the first form of ``_hints_in`` asked each cluster apart."""
    out = []
    m = 0.25 * est.layout.side
    for k, cl in enumerate(clusters):
        b = est.layout.bounds[cl.members]
        on = ((hints[:, None, 0] >= b[None, :, 0] - m) & (hints[:, None, 0] <= b[None, :, 2] + m)
              & (hints[:, None, 1] >= b[None, :, 1] - m) & (hints[:, None, 1] <= b[None, :, 3] + m)).any(axis=1)
        sound = np.all(np.isfinite(hints), axis=1) & (hints[:, 2] > 0) & (hints[:, 3] > 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            size_ok = np.abs(np.log(hints[:, 2] / float(d_start[k]))) <= math.log(2.0)
        h = hints[on & sound & size_ok]
        if h.shape[0] > 1:
            cx, cy = cl.centroid
            h = h[np.argsort(np.hypot(h[:, 0] - cx, h[:, 1] - cy))]
        out.append(h)
    return out


presses = st.lists(st.tuples(st.floats(-0.02, 0.18), st.floats(-0.02, 0.18), st.floats(0.05, 8.0),
                             st.floats(0.004, 0.05)), min_size=1, max_size=5)
hint_rows = st.lists(st.tuples(st.floats(-0.03, 0.19), st.floats(-0.03, 0.19),
                               st.sampled_from([0.0, -0.01, math.nan, math.inf, 0.005, 0.01, 0.02, 0.04]),
                               st.sampled_from([0.0, math.nan, 0.1, 1.0, 3.0])), max_size=8)


#: hints near a press (the previous frame's contacts: one or two per press, moved a little)
near = st.lists(st.tuples(st.integers(0, 4), st.floats(-0.012, 0.012), st.floats(-0.012, 0.012),
                          st.floats(0.5, 2.2)), max_size=8)


@given(presses, hint_rows, near, st.integers(0, 2**32 - 1), st.booleans())
def test_the_set_up_in_one_pass_is_the_set_up_a_cluster_at_a_time(press, hints, moved, seed, holes):
    lay = grid_layout(5, 5)
    est = ContactEstimator(lay, noise=2e-15)
    disks: list[tuple[float, float, float, float]] = []
    for x, y, f, d in press:  # (disks that do not overlap one another, as skin_response needs)
        if all(math.hypot(x - u, y - v) > 0.5 * (d + e) for u, v, _, e in disks):
            disks.append((x, y, f, d))
    dc1, dc2 = skin_response(lay, disks)
    rng = np.random.default_rng(seed)
    dc1 = dc1 + rng.normal(0.0, 2e-15, lay.n)
    dc2 = dc2 + rng.normal(0.0, 2e-15, lay.n)
    if holes:  # elements with no reading: clusters joined around them, rings without them
        gone = rng.choice(lay.n, size=3, replace=False)
        dc1[gone] = np.nan
    hints = hints + [(disks[i % len(disks)][0] + dx, disks[i % len(disks)][1] + dy, disks[i % len(disks)][3] * g,
                      disks[i % len(disks)][2]) for i, dx, dy, g in moved]
    h = np.array(hints, dtype=np.float64).reshape(-1, 4)
    seen: list[tuple[list[Cluster], np.ndarray]] = []
    fit_valid = est._fit_valid

    def spy(clusters: list[Cluster], hs: np.ndarray) -> list:
        seen.append((clusters, hs))
        return fit_valid(clusters, hs)

    est._fit_valid = spy  # type: ignore[method-assign, assignment]
    est.estimate(dc1, dc2, hints=h)
    for clusters, hs in seen:
        st_fast = est._runner.starts(clusters)
        np.testing.assert_array_equal(st_fast, _plain_starts(est._runner, clusters))
        d_start = 2.0 * st_fast[:, 2]
        got = est._hints_in(clusters, hs, d_start) if hs.shape[0] else []
        want = _plain_hints_in(est, clusters, hs, d_start) if hs.shape[0] else []
        assert len(got) == len(want)
        for g, w in zip(got, want):
            assert g.shape == w.shape
            np.testing.assert_array_equal(g, w)
        for cl in clusters:
            assert cl.ring_reads == (cl.quiet is not None and not bool(cl.quiet[cl.members.size:].all()))


@given(presses, st.integers(0, 2**32 - 1), st.lists(st.integers(0, 24), min_size=1, max_size=25, unique=True),
       st.floats(0.0, 3.0))
def test_an_inverse_of_the_skin_taken_by_rows_is_the_inverse_of_those_rows(press, seed, rows, scale):
    """A band's second chart takes its elements' inverse from the skin's (Inverse.rows):
    the same arrays as its own inverse of those elements' readings, ``firm`` None alike."""
    lay = grid_layout(5, 5)
    est = ContactEstimator(lay, noise=2e-15)
    dc1, dc2 = skin_response(lay, [(x, y, f * 10.0 ** scale, d) for x, y, f, d in press[:1]])
    rng = np.random.default_rng(seed)
    c1 = (dc1 * rng.uniform(0.5, 2.0, lay.n) + rng.normal(0.0, 2e-15, lay.n))[None]
    c2 = (dc2 * rng.uniform(0.5, 2.0, lay.n) + rng.normal(0.0, 2e-15, lay.n))[None]
    act = (rng.random(lay.n) < 0.7)[None] & ((c1 > 6e-15) | (c2 > 6e-15))
    r = np.array(sorted(rows), dtype=np.int64)
    got = est._inverse(c1, c2, act).rows(r)
    sub = ContactEstimator(grid_layout(1, r.size), noise=2e-15)  # (another layout of as many elements)
    want = sub._inverse(c1[:, r], c2[:, r], act[:, r])
    for g, w in zip(got, want):
        assert (g is None) == (w is None)
        if g is not None:
            np.testing.assert_array_equal(g, w)


def _plain_components(n: int, e: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Labels by numpy's min-label propagation with pointer jumping (cluster_elements' first form)."""
    lab = np.arange(n)
    while True:
        m = np.minimum(lab[e[:, 0]], lab[e[:, 1]])
        new = lab.copy()
        np.minimum.at(new, e[:, 0], m)
        np.minimum.at(new, e[:, 1], m)
        new = new[new]
        if np.array_equal(new, lab):
            break
        lab = new
    out = np.full(n, -1, dtype=np.int64)
    roots = np.unique(lab[a])
    out[a] = np.searchsorted(roots, lab[a])
    return out


@given(st.integers(1, 9), st.integers(1, 9), st.integers(0, 2**32 - 1), st.floats(0.0, 1.0),
       st.sampled_from(["edge", "corner"]), st.floats(0.0, 0.4))
def test_the_compiled_components_are_numpys_labels(rows, cols, seed, density, connectivity, holes):
    """cluster_elements' labels (compiled union-find) are those of numpy's propagation, on
    random touches of a grid, with and without unknown elements between them."""
    from cellbridge.tactile.clusters import _across_unknown, cluster_elements

    lay = grid_layout(rows, cols)
    rng = np.random.default_rng(seed)
    a = rng.random(lay.n) < density
    e = lay.edges if connectivity == "edge" else lay.corner_edges
    e = e[a[e[:, 0]] & a[e[:, 1]]]
    np.testing.assert_array_equal(cluster_elements(lay, a, connectivity), _plain_components(lay.n, e, a))
    u = (rng.random(lay.n) < holes) & ~a
    eu = np.concatenate([e, _across_unknown(lay, a, u)])
    np.testing.assert_array_equal(cluster_elements(lay, a, connectivity, unknown=u), _plain_components(lay.n, eu, a))


@given(presses, st.integers(0, 2**32 - 1), st.floats(0.0, 1.0))
def test_clusters_left_out_as_replaced_are_those_wholly_on_replaced_elements(press, seed, share):
    """frame_clusters(replaced=...) poses the clusters a filter of the whole list keeps
    (a member not replaced), each as the whole list has it."""
    from cellbridge.tactile.clusters import cluster_elements

    lay = grid_layout(6, 6)
    runner = FitRunner(lay, ElementParams(side=lay.side), np.full(2, 2e-15), False)
    rng = np.random.default_rng(seed)
    c1, c2 = skin_response(lay, [(x, y, f, d) for x, y, f, d in press[:1]])
    act = (rng.random(lay.n) < 0.35) | (c1 > 5e-14)
    labels = cluster_elements(lay, act)
    valid = act & (rng.random(lay.n) < 0.8)
    force = np.where(valid, rng.uniform(0.1, 3.0, lay.n), np.nan)
    area = np.where(valid, rng.uniform(1e-5, 1e-3, lay.n), np.nan)
    fin = np.ones(lay.n, dtype=bool)
    replaced = rng.random(lay.n) < share
    every = runner.frame_clusters(labels, c1, c2, fin, valid, force, area, None, np.full(2, 2e-15))
    want = [cl for cl in every if not replaced[cl.members].all()]
    got = runner.frame_clusters(labels, c1, c2, fin, valid, force, area, None, np.full(2, 2e-15), replaced)
    assert len(got) == len(want)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g.obs, w.obs)
        np.testing.assert_array_equal(g.y, w.y)
        assert g.base == w.base and g.valid == w.valid


def test_read_only_flags_reach_the_components_kernel_as_its_one_signature() -> None:
    """An ``active`` (or ``unknown``) array a caller made read-only is another array type to
    numba: passed as it was, the kernel compiled a second signature at its first call (a
    latency spike mid-run), which the warm-up never loads."""
    from cellbridge.tactile.cluster_kernel import components
    from cellbridge.tactile.clusters import cluster_elements

    layout = grid_layout(3, 3)
    active = np.zeros(layout.n, dtype=bool)
    active[[0, 1, 4]] = True
    cluster_elements(layout, active.copy())  # the signature every caller gives
    before = len(components.signatures)
    active.flags.writeable = False
    unknown = np.zeros(layout.n, dtype=bool)
    unknown.flags.writeable = False
    labels = cluster_elements(layout, active, unknown=unknown)
    assert labels.tolist() == [0, 0, -1, -1, 0, -1, -1, -1, -1]
    assert len(components.signatures) == before, components.signatures
