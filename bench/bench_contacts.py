"""Contact estimation at frame rate: accuracy at 1 fF noise, time per contact and per frame.

Prints tables; asserts nothing. Run (one core, about a minute):

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_contacts.py [--against REV]

* Accuracy: random contacts straddling the seams of the 2×2 skin (D 10-30 mm,
  F 2-10 N, half across one seam, half near the corner), Gaussian noise of 1 fF on
  every reading: RMS position error on the axes the readings resolve (contacts
  with a valid pressure), force error at p95 over those, and how often the
  reported σ covers the error (|error| ≤ 2σ, per axis, every axis of every fitted
  contact counted, light touches included). Light touches (the inverse's ambiguous
  low-pressure region: the position is an interval) are reported apart.
* Speed, uniform model: one random contact per frame anywhere on a 4×4 and a
  16×16 skin (D 10-30 mm, F 2-10 N, 1 fF noise; ``active`` = elements the contact
  really touches, as the calibrator's touch flags give), ``estimate()`` per frame;
  a 16×16 frame with 8 simultaneous contacts; the spread model (s = 2 mm) per
  contact; the tracker's ``update()`` on the 8-contact frames; ``estimate_frames()``
  on chunks of the same frames (time per frame; its p99 is over chunks). The estimator
  of another git revision (``--against REV``; default: the one before the compiled
  kernel) runs on the same readings in the same run, in a process of its own on that
  revision's package, for the speed-up.
* Speed on readings the model did not make: one random contact per frame on a 4×4
  skin (D 8-30 mm, F 2-15 N, 1 fF noise), the same disks read four ways: made by the
  fitted model itself; each element's overlap integrated independently on a 0.1 mm
  grid anchored at the disk's centre; that, with a gain error per element and
  channel (3 % rms); and the spread model's readings (s = 2 mm) fitted with the
  uniform one. Per kind of contact (inside one element, across one seam, on a
  corner), the RMS position error on the axes the readings resolve, and how often
  one press came back as more contacts than it has clusters (a split that is none).

Times are wall clock (``perf_counter``) and CPU time of this thread
(``thread_time``): the machine is shared, so the wall p99 includes time other
processes held the core; the CPU figures are what the estimator itself costs.
The numba kernels are compiled (or loaded from their cache) before timing.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import pickle  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

# The package's public names only: the same script runs on an older revision (--against).
from cellbridge.tactile import ContactEstimator, cluster_elements, grid_layout, skin_response  # noqa: E402

from timing import pin_to_one_core, revision_tree, run_at_revision, table  # noqa: E402

#: The estimator before the compiled fit kernel (commit de1ca21): what --against compares with by default.
BEFORE_KERNEL = "de1ca21^"

MM = 1e-3
NOISE = 1e-15
SPREAD = 0.002
SEPARATION: list[list[object]] = []
LEGACY: list[tuple] = []  # (rows, [skin, frames], (rows, cols), spread, frames, today's CPU median) for --against


def noisy(lay, contacts, rng, spread=0.0):
    dc1, dc2 = skin_response(lay, contacts, spread=spread)
    active = (dc1 > 3 * NOISE) | (dc2 > 3 * NOISE)
    return dc1 + rng.normal(0, NOISE, lay.n), dc2 + rng.normal(0, NOISE, lay.n), active


def random_disk(rng, lo, hi):
    d = rng.uniform(0.010, 0.030)
    x, y = rng.uniform(lo, hi, 2)
    return [x, y, rng.uniform(2.0, 10.0), d]


def timed(fn, frames):
    wall, cpu, out = [], [], []
    for f in frames:
        t0, c0 = time.perf_counter(), time.thread_time()
        out.append(fn(*f))
        cpu.append(time.thread_time() - c0)
        wall.append(time.perf_counter() - t0)
    return np.array(wall), np.array(cpu), out


def ms(a, q=50):
    return f"{1e3 * np.percentile(a, q):.3f}"


def accuracy(n=300):
    rng = np.random.default_rng(5)
    lay = grid_layout(2, 2)
    est = ContactEstimator(lay, noise=NOISE)
    err_l: list[float] = []
    light_l: list[float] = []
    ferr: list[float] = []
    cover, axes, n_fit = 0, 0, 0
    for _ in range(n):
        d = rng.uniform(0.010, 0.030)
        f = rng.uniform(2.0, 10.0)
        x, y = rng.uniform(0.020 - d / 2, 0.020 + d / 2, 2)
        if rng.uniform() < 0.5:
            y = rng.uniform(-0.015 + d / 2, 0.015 - d / 2)
        dc1, dc2, _ = noisy(lay, [x, y, f, d], rng)
        cs = est.estimate(dc1, dc2)
        if len(cs) != 1 or not cs[0].fit_ok:
            continue
        c = cs[0]
        n_fit += 1
        if c.valid:
            ferr.append(abs(c.force / f - 1.0))
        for ax, (t, e, s) in enumerate(((x, c.x, c.sigma_x), (y, c.y, c.sigma_y))):
            axes += 1
            cover += abs(e - t) <= 2 * s
            if c.observable[ax] and c.valid:
                err_l.append(e - t)
            elif c.observable[ax]:
                light_l.append(e - t)
    err = np.array(err_l)
    light = np.array(light_l)
    table(
        "Accuracy: random straddling contacts on the 2×2 skin, 1 fF Gaussian noise per reading",
        ["contacts", "fitted", "valid", "resolved axes (valid)", "RMS err mm", "max err mm", "F err p95 %",
         "σ covers (2σ, all axes) %", "light-touch axes", "their RMS err mm"],
        [[n, n_fit, len(ferr), err.size, f"{math.sqrt(np.mean(err ** 2)) / MM:.4f}",
          f"{np.max(np.abs(err)) / MM:.4f}", f"{100 * np.percentile(ferr, 95):.3f}", f"{100 * cover / axes:.1f}",
          light.size, f"{math.sqrt(np.mean(light ** 2)) / MM:.2f}" if light.size else "-"]],
    )


GRID = 1e-4  # the independent integration's cell (0.1 mm)
GAIN = 0.03  # rms gain error per element and channel


def grid_response(lay, contact):
    """(ΔC1, ΔC2) of one uniform disk, each element's overlap counted on a 0.1 mm grid
    of cell centres anchored at the disk's centre (not at the element edges): an
    integration independent of the fit's closed-form overlap."""
    from cellbridge.tactile.element import sensitivity  # here: --against runs this script on older trees

    x, y, f, d = contact
    r = 0.5 * d
    g1, g2 = sensitivity(np.array([f / (math.pi * r * r)]))
    k = np.arange(-math.ceil(r / GRID) - 1, math.ceil(r / GRID) + 2) * GRID
    px, py = np.meshgrid(x + k, y + k, indexing="ij")
    inside = (px - x) ** 2 + (py - y) ** 2 <= r * r
    idx = lay.element_at(np.stack([px[inside], py[inside]], axis=-1))
    area = np.bincount(idx[idx >= 0], minlength=lay.n) * GRID * GRID
    return area * g1[0], area * g2[0]


def perturbed_sets(lay, n, rng):
    """The same n disks read four ways (see the module docstring), with their kinds."""
    from cellbridge.tactile.overlap import disk_element_overlap  # here: --against runs this script on older trees

    ext = lay.extent
    disks = [[*rng.uniform(ext[0] + 0.004, ext[2] - 0.004, 2), rng.uniform(2.0, 15.0), rng.uniform(0.008, 0.030)]
             for _ in range(n)]
    names = ("model-made (uniform)", "grid-integrated overlap", f"grid + {100 * GAIN:.0f} % gain error",
             f"spread s = {SPREAD / MM:.0f} mm, fitted uniform")
    sets: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {name: [] for name in names}
    for c in disks:
        gains = 1.0 + rng.normal(0.0, GAIN, (2, lay.n))
        grid = grid_response(lay, c)
        for name, (d1, d2) in zip(names, (skin_response(lay, c), grid, (grid[0] * gains[0], grid[1] * gains[1]),
                                          skin_response(lay, c, spread=SPREAD))):
            sets[name].append((d1 + rng.normal(0, NOISE, lay.n), d2 + rng.normal(0, NOISE, lay.n)))
    touched = np.array([(disk_element_overlap(lay, [c[:2]], [0.5 * c[3]])[0] > 0).sum() for c in disks])
    kinds = np.where(touched == 1, 0, np.where(touched == 2, 1, 2))
    return disks, sets, kinds


def speed_perturbed(rng, n=300):
    lay = grid_layout(4, 4)
    disks, sets, kinds = perturbed_sets(lay, n, rng)
    whole = ContactEstimator(lay, noise=NOISE, split=False)
    warm = ContactEstimator(lay, noise=NOISE)
    for frames in sets.values():  # every code path compiled or loaded before any timing
        for f in frames[:50]:
            warm.estimate(*f)
    rows = []
    for name, frames in sets.items():
        est = ContactEstimator(lay, noise=NOISE)
        for f in frames[:20]:
            est.estimate(*f)
        wall, cpu, out = timed(est.estimate, frames)
        err = []
        for c, (x, y, _, _) in zip(out, disks):
            if len(c) == 1 and c[0].valid and c[0].fit_ok:
                err += [e - t for e, t, seen in ((c[0].x, x, c[0].observable[0]), (c[0].y, y, c[0].observable[1]))
                        if seen]
        split = sum(len(o) > len(whole.estimate(*f)) for o, f in zip(out, frames))
        rows.append([name, n, ms(wall), ms(wall, 99), ms(cpu), ms(cpu, 99),
                     *(ms(cpu[kinds == k]) for k in range(3)),
                     f"{math.sqrt(np.mean(np.square(err))) / MM:.3f}", f"{100 * split / n:.1f}"])
    table(
        "Time per contact on readings the model did not make (4×4, one contact per frame, D 8-30 mm, "
        "F 2-15 N, 1 fF noise); targets: median ≤ 0.5, p99 ≤ 2",
        ["readings", "n", "wall median", "wall p99", "CPU median", "CPU p99",
         f"CPU median inside ({(kinds == 0).sum()})", f"seam ({(kinds == 1).sum()})",
         f"corner ({(kinds == 2).sum()})", "RMS err resolved axes mm", "split %"],
        rows,
    )


def batched(rows, est, name, what, frames, chunk):
    """estimate_frames() on chunks of frames: time per frame."""
    groups = [frames[i : i + chunk] for i in range(0, len(frames) - chunk + 1, chunk)]
    stacked = [tuple(np.stack([f[j] for f in g]) for j in range(3)) for g in groups]
    wall, cpu, out = timed(est.estimate_frames, stacked)
    per = np.mean([len(c) for o in out for c in o])
    rows.append([name, f"{what}, estimate_frames × {chunk}", len(groups) * chunk, ms(wall / chunk),
                 ms(wall / chunk, 99), ms(cpu / chunk), ms(cpu / chunk, 99), f"{per:.2f}"])


def speed_single(rows, rows_legacy, name, lay, n, n_legacy, rng):
    pitch = lay.side
    extent = lay.extent
    frames = [noisy(lay, random_disk(rng, extent[0] + 0.1 * pitch, extent[2] - 0.1 * pitch), rng) for _ in range(n)]
    est = ContactEstimator(lay, noise=NOISE)
    for f in frames[:20]:
        est.estimate(*f)
    wall, cpu, out = timed(est.estimate, frames)
    per = np.array([len(o) for o in out])
    rows.append([name, "one contact per frame", n, ms(wall), ms(wall, 99), ms(cpu), ms(cpu, 99),
                 f"{per.mean():.2f}"])
    batched(rows, est, name, "one contact per frame", frames, 50)
    side = math.isqrt(lay.n)
    LEGACY.append((rows_legacy, [name, "one contact per frame"], (side, side), 0.0, frames[:n_legacy],
                   np.median(cpu[:n_legacy])))
    return est


def speed_frame8(rows, rows_legacy, rng, n=200, n_legacy=10):
    lay = grid_layout(16, 16)
    frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    while len(frames) < n:
        disks: list[list[float]] = []
        while len(disks) < 8:
            d = random_disk(rng, 0.0, 0.600)
            # Separate fingers: footprints at least a pitch apart (touching pairs are
            # the split test's business, not this timing).
            if all(math.hypot(d[0] - e[0], d[1] - e[1]) > 0.5 * (d[3] + e[3]) + 0.040 for e in disks):
                disks.append(d)
        frames.append(noisy(lay, disks, rng))
    est = ContactEstimator(lay, noise=NOISE)
    for f in frames[:10]:
        est.estimate(*f)
    wall, cpu, out = timed(est.estimate, frames)
    per = np.array([len(o) for o in out])
    rows.append(["16×16", "8 contacts per frame", n, ms(wall), ms(wall, 99), ms(cpu), ms(cpu, 99),
                 f"{per.mean():.2f}"])
    batched(rows, est, "16×16", "8 contacts per frame", frames, 10)
    # Fingers 40 mm apart edge to edge can still press neighbouring elements: their
    # clusters merge, and the two-disk split has to separate them.
    ncl = np.array([cluster_elements(lay, f[2]).max() + 1 for f in frames])
    SEPARATION.append(["16×16, 8 fingers", n, f"{ncl.mean():.2f}", int((ncl < 8).sum()),
                       int(((ncl < 8) & (per == 8)).sum()), f"{per.mean():.2f}"])
    LEGACY.append((rows_legacy, ["16×16", "8 contacts per frame"], (16, 16), 0.0, frames[:n_legacy],
                   np.median(cpu[:n_legacy])))
    from cellbridge.tactile import ContactTracker  # (not at every revision --against may run)

    tr = ContactTracker(est, birth_frames=1)
    # The tracker sees the same fingers frame after frame: replay each frame 5 times.
    replay = [f for f in frames[:40] for _ in range(5)]
    tw, tc, _ = timed(tr.update, replay)
    rows.append(["16×16", "8 contacts, tracker.update (warm)", len(replay), ms(tw), ms(tw, 99), ms(tc),
                 ms(tc, 99), "8"])


def speed_spread(rows, rows_legacy, rng, n=60, n_legacy=4):
    lay = grid_layout(2, 2)
    frames = []
    for _ in range(n):
        d = rng.uniform(0.010, 0.020)
        x = rng.uniform(0.020 - 0.4 * d, 0.020 + 0.4 * d)
        frames.append(noisy(lay, [x, rng.uniform(-0.01, 0.01), rng.uniform(2.0, 8.0), d], rng, spread=SPREAD))
    t0 = time.perf_counter()
    est = ContactEstimator(lay, noise=NOISE, spread=SPREAD)  # builds the profile rows
    est.estimate(*frames[0])
    cold = time.perf_counter() - t0
    for f in frames[:10]:
        est.estimate(*f)
    wall, cpu, out = timed(est.estimate, frames)
    rows.append(["2×2", f"spread s = {SPREAD / MM:.0f} mm, one contact", n, ms(wall), ms(wall, 99), ms(cpu),
                 ms(cpu, 99), f"{np.mean([len(o) for o in out]):.2f}"])
    LEGACY.append((rows_legacy, ["2×2", f"spread s = {SPREAD / MM:.0f} mm, one contact"], (2, 2), SPREAD,
                   frames[:n_legacy], np.median(cpu[:n_legacy])))
    return cold


def estimate_only() -> None:
    """``--estimate-only``, run by ``--against`` on the other revision's package: each job
    on stdin ((rows, cols), spread, frames) timed with that revision's estimator."""
    pin_to_one_core()
    out = []
    for (r, c), spread, frames in pickle.load(sys.stdin.buffer):
        lay = grid_layout(r, c)
        est = ContactEstimator(lay, noise=NOISE, spread=spread) if spread else ContactEstimator(lay, noise=NOISE)
        wall, cpu, _ = timed(est.estimate, frames)
        out.append((wall, cpu))
    pickle.dump(out, sys.stdout.buffer)


def against(rev: str) -> None:
    """The same frames through the estimator of git revision ``rev``, in a process of its own."""
    jobs = [(shape, spread, frames) for _, _, shape, spread, frames, _ in LEGACY]
    with tempfile.TemporaryDirectory() as d:
        tree = revision_tree(rev, Path(__file__).resolve().parents[1], Path(d))
        got = pickle.loads(run_at_revision(tree, __file__, ["--estimate-only"], pickle.dumps(jobs)))
    for (rows, head, _, _, frames, today), (lw, lc) in zip(LEGACY, got):
        rows.append([*head, len(frames), ms(lw), ms(lc), f"{np.median(lc) / today:.0f}×"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--against", default=BEFORE_KERNEL, metavar="REV",
                    help=f"git revision whose estimator runs on the same frames (default {BEFORE_KERNEL}: "
                         "the estimator before the compiled kernel); '' skips it")
    ap.add_argument("--estimate-only", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.estimate_only:
        estimate_only()
        return
    pin_to_one_core()
    t0 = time.perf_counter()
    print("cellbridge contact estimation bench — 40 mm elements, 1 fF noise, one core")
    accuracy()
    rng = np.random.default_rng(11)
    rows: list[list[object]] = []
    rows_legacy: list[list[object]] = []
    speed_single(rows, rows_legacy, "4×4", grid_layout(4, 4), 400, 40, rng)
    speed_single(rows, rows_legacy, "16×16", grid_layout(16, 16), 400, 20, rng)
    speed_frame8(rows, rows_legacy, rng)
    cold = speed_spread(rows, rows_legacy, rng)
    speed_perturbed(np.random.default_rng(21))
    if args.against:
        against(args.against)
    table(
        "Time per estimate() call (ms; uniform model unless stated); targets: one contact median ≤ 0.5, "
        "p99 ≤ 2; 8 contacts ≤ 4; spread ≤ 5",
        ["skin", "frames", "n", "wall median", "wall p99", "CPU median", "CPU p99", "contacts/frame"],
        rows,
    )
    table(
        f"The estimator at git revision {args.against or '-'} on the first frames of the same sets",
        ["skin", "frames", "n", "wall median", "CPU median", "speed-up (CPU medians)"],
        rows_legacy,
    )
    table(
        "Touching fingers: frames whose clusters merged, and how many came back as all 8 contacts "
        "(two disks per cluster at most)",
        ["skin", "frames", "clusters/frame", "frames with merged clusters", "of them all 8 found", "contacts/frame"],
        SEPARATION,
    )
    print(f"\nspread model, construction and first contact of the process (profile rows built): "
          f"{1e3 * cold:.0f} ms")
    print(f"total bench time {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
