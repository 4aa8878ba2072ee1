"""The estimator's results pinned on a fixed set of frames: a faster estimate must give the same.

Every field of every contact (positions, forces, σ, covariance, light-touch intervals, the
elements, the flags) of :class:`~cellbridge.tactile.estimator.ContactEstimator` on frames that
take each of its paths: one contact on a 4×4 from the model's own readings and from readings
with a gain error per element and channel, light touches (located and unlocated), hard
presses (the firm-force profile), two touching fingers (the split), elements with no reading
and hints (clusters joined across an unknown element, and kept apart by hints), warm starts
in the wrong place (the redo), the spread model, the area method, corner connectivity,
``estimate_frames``, and ten contacts on the humanoid's 1 144 elements.

The frames (readings, flags, hints) and the layouts are stored with the results
(``tests/data/estimate_pins.npz`` and ``.json``), so the pins do not move when the response
model or the skin description does. Floats must agree to 1e-9 relative (a reordered sum
may move the last bits); everything else exactly. Regenerate, only for an intended change
of results, with ``.venv/bin/python tests/test_tactile_estimate_pins.py --regenerate``.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cellbridge.tactile.estimator import ContactEstimator
from cellbridge.tactile.layout import SkinLayout, grid_layout

DATA = Path(__file__).with_name("data")
INPUTS = DATA / "estimate_pins.npz"
RESULTS = DATA / "estimate_pins.json"
NOISE = 1e-15
ENTER = 5e-14  #: the calibration's default touch threshold per channel (F)
REL = 1e-9
#: absolute floor per field, for values that are zero up to float order (m, m², N, ...)
ABS = {"cov": 1e-26}
ABS_DEFAULT = 1e-15

#: case name -> (layout key, estimator options, whether the case runs ``estimate_frames``)
CASES: dict[str, tuple[str, dict[str, Any], bool]] = {
    "own_4x4": ("4x4", {}, False),
    "gain_4x4": ("4x4", {}, False),
    "light_4x4": ("4x4", {}, False),
    "ring_4x4": ("4x4", {}, False),
    "hard_4x4": ("4x4", {}, False),
    "two_fingers_4x4": ("4x4", {}, False),
    "unknown_hints_4x4": ("4x4", {}, False),
    "warm_starts_4x4": ("4x4", {}, False),
    "spread_2x2": ("2x2", {"spread": 0.002}, False),
    "area_3x3": ("3x3", {"method": "area"}, False),
    "corner_4x4": ("4x4", {"connectivity": "corner"}, False),
    "no_model_error_4x4": ("4x4", {"model_error": 0.0}, False),
    "frames_4x4": ("4x4", {}, True),
    "humanoid_own": ("humanoid", {}, False),
    "humanoid_gain": ("humanoid", {}, False),
}


def _layouts(inputs: Any) -> dict[str, SkinLayout]:
    return {
        "2x2": grid_layout(2, 2), "3x3": grid_layout(3, 3), "4x4": grid_layout(4, 4),
        "humanoid": SkinLayout(inputs["humanoid_centres"], side=float(inputs["humanoid_side"]),
                               ids=inputs["humanoid_ids"]),
    }


def _run(inputs: dict[str, np.ndarray]) -> dict[str, list[list[dict[str, Any]]]]:
    """Every case's contacts, per frame, as plain dicts."""
    lays = _layouts(inputs)
    out: dict[str, list[list[dict[str, Any]]]] = {}
    for name, (lay_key, options, batched) in CASES.items():
        est = ContactEstimator(lays[lay_key], noise=NOISE, **options)
        c1, c2 = inputs[f"{name}.c1"], inputs[f"{name}.c2"]
        act = inputs[f"{name}.active"] if f"{name}.active" in inputs else None
        if batched:
            frames = est.estimate_frames(c1, c2, act)
        else:
            frames = []
            for t in range(c1.shape[0]):
                hints = inputs.get(f"{name}.hints{t}")
                frames.append(est.estimate(c1[t], c2[t], None if act is None else act[t], hints=hints))
        out[name] = [[c.to_dict() for c in cs] for cs in frames]
    return out


def _same(a: Any, b: Any, field: str) -> bool:
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(_same(x, y, field) for x, y in zip(a, b))
    if isinstance(a, bool) or isinstance(b, bool) or isinstance(a, int) and isinstance(b, int):
        return type(a) is type(b) and a == b
    a, b = float(a), float(b)
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return math.isclose(a, b, rel_tol=REL, abs_tol=ABS.get(field, ABS_DEFAULT))


@pytest.fixture(scope="module")
def got() -> dict[str, list[list[dict[str, Any]]]]:
    with np.load(INPUTS) as inputs:
        return _run(dict(inputs))


@pytest.mark.parametrize("case", list(CASES))
def test_results_are_the_pinned_ones(case: str, got: dict[str, list[list[dict[str, Any]]]]) -> None:
    want = json.loads(RESULTS.read_text())[case]
    mine = got[case]
    assert len(mine) == len(want)
    for t, (cs, ws) in enumerate(zip(mine, want)):
        assert len(cs) == len(ws), f"frame {t}: {len(cs)} contacts, pinned {len(ws)}"
        for j, (c, w) in enumerate(zip(cs, ws)):
            assert set(c) == set(w)
            bad = [k for k in w if not _same(c[k], w[k], k)]
            assert not bad, f"frame {t} contact {j}: " + ", ".join(f"{k} {c[k]!r} != pinned {w[k]!r}" for k in bad)


def test_the_pins_take_the_estimators_paths() -> None:
    """The frames exercise what they are named for (else a broken path would pass unseen)."""
    want = json.loads(RESULTS.read_text())
    flat = {name: [c for cs in frames for c in cs] for name, frames in want.items()}
    assert any(not c["valid"] and c["fit_ok"] for c in flat["light_4x4"])  # a located light touch
    assert any(not c["valid"] and not c["fit_ok"] for c in flat["light_4x4"])  # an unlocated one
    assert any(c["valid"] and c["fit_ok"] and not c["observable"][0] for cs in want.values()
               for c in (x for f in cs for x in f))
    two = [len(cs) for cs in want["two_fingers_4x4"]]
    assert max(two) == 2  # split into two disks
    assert all(len(cs) == 10 for cs in want["humanoid_own"])
    assert all(len(cs) == 10 for cs in want["humanoid_gain"])
    assert any(c["valid"] and c["pressure"] > 1e5 for c in flat["hard_4x4"])
    assert any(c["valid"] and c["fit_ok"] and any(c["observable"]) for c in flat["ring_4x4"])
    assert all(c["valid"] for c in flat["area_3x3"])


# ---------------------------------------------------------------------------- generation


def _generate() -> None:  # pragma: no cover - run by hand, see the module's docstring
    """The frames and today's results (only for an intended change of results)."""
    from cellbridge.daemon.shell.skin_file import load_skin
    from cellbridge.tactile.response import skin_response

    root = Path(__file__).resolve().parents[1]
    hum = load_skin(root / "cellbridge" / "skins" / "humanoid.toml").layout()
    inputs: dict[str, np.ndarray] = {"humanoid_centres": np.asarray(hum.centres), "humanoid_side": np.array(hum.side),
                                     "humanoid_ids": np.asarray(hum.ids)}
    lays = _layouts(inputs)
    rng = np.random.default_rng(20261129)

    def read(lay: SkinLayout, cs: list[list[float]], gain: float = 0.0, spread: float = 0.0) -> tuple[Any, Any]:
        d1, d2 = skin_response(lay, cs, spread=spread)
        if gain:
            g = 1.0 + rng.normal(0.0, gain, (2, lay.n))
            d1, d2 = d1 * g[0], d2 * g[1]
        return d1 + rng.normal(0, NOISE, lay.n), d2 + rng.normal(0, NOISE, lay.n)

    def disk(lay: SkinLayout, f: tuple[float, float] = (2.0, 10.0), d: tuple[float, float] = (0.010, 0.025),
             at: int | None = None, off: float = 0.015) -> list[float]:
        r = int(rng.integers(lay.n)) if at is None else at
        return [*(lay.centres[r] + rng.uniform(-off, off, 2)), rng.uniform(*f), rng.uniform(*d)]

    def put(name: str, frames: list[tuple[Any, Any]], active: bool = False,
            hints: list[np.ndarray | None] | None = None) -> None:
        inputs[f"{name}.c1"] = np.array([f[0] for f in frames])
        inputs[f"{name}.c2"] = np.array([f[1] for f in frames])
        if active:
            inputs[f"{name}.active"] = (inputs[f"{name}.c1"] > ENTER) | (inputs[f"{name}.c2"] > ENTER)
        for t, h in enumerate(hints or []):
            if h is not None:
                inputs[f"{name}.hints{t}"] = np.asarray(h, dtype=np.float64).reshape(-1, 4)

    g4 = lays["4x4"]
    put("own_4x4", [read(g4, [disk(g4)]) for _ in range(12)])
    put("gain_4x4", [read(g4, [disk(g4)], gain=0.03) for _ in range(12)], active=True)
    light = []
    for t in range(14):  # across a seam (located), or inside one element (unlocated)
        c = disk(g4, f=(0.15, 0.4), d=(0.008, 0.016), at=int(rng.integers(16)), off=0.0)
        if t % 3:
            c[0] += 0.02 * rng.choice([-1, 1]) + rng.uniform(-0.4, 0.4) * c[3]
        light.append(read(g4, [c]))
    put("light_4x4", light)
    ring = []
    for _ in range(8):  # a footprint reaching a fraction of a millimetre onto a quiet neighbour
        c = disk(g4, at=int(rng.choice([5, 6, 9, 10])), off=0.0)
        c[0] += rng.choice([-1, 1]) * (0.02 - 0.5 * c[3] + rng.uniform(0.0002, 0.001))
        ring.append(read(g4, [c]))
    put("ring_4x4", ring, active=True)
    put("hard_4x4", [read(g4, [disk(g4, f=(20.0, 60.0), d=(0.003, 0.006))]) for _ in range(8)])
    two = []
    for _ in range(8):
        a = disk(g4, d=(0.010, 0.016), at=5, off=0.008)
        b = [a[0] + rng.choice([-1, 1]) * 0.026, a[1] + rng.uniform(-0.004, 0.004), rng.uniform(2, 10),
             rng.uniform(0.010, 0.016)]
        two.append(read(g4, [a, b]))
    put("two_fingers_4x4", two)
    frames, hints = [], []
    for t in range(10):
        cs = [disk(g4, at=int(rng.integers(16)), off=0.019)]
        if t % 2:
            far = (int(np.argmin(np.abs(g4.centres - cs[0][:2]).sum(axis=1))) + 10) % 16
            cs.append(disk(g4, at=far, off=0.01))
        d1, d2 = read(g4, cs)
        unk = rng.choice(16, 2 + t % 3, replace=False)
        d1[unk] = np.nan
        if t % 4 == 3:
            d2[unk[0]] = np.nan
        frames.append((d1, d2))
        h = np.array([[c[0], c[1], c[3], c[2]] for c in cs])
        if t % 3 == 1:
            h[0, 2:] = np.nan  # a hint that only says where a contact was
        hints.append(h if t % 5 else None)
    put("unknown_hints_4x4", frames, hints=hints)
    frames, hints = [], []
    for t in range(14):
        c = disk(g4)
        frames.append(read(g4, [c]))
        shift = 0.0 if t % 3 == 0 else rng.uniform(0.008, 0.02) * rng.choice([-1, 1])
        hints.append(np.array([[c[0] + shift, c[1], c[3] * rng.uniform(0.7, 1.4), c[2] * rng.uniform(0.5, 2)]]))
    put("warm_starts_4x4", frames, hints=hints)
    g2 = lays["2x2"]
    put("spread_2x2", [read(g2, [disk(g2, off=0.012)], spread=0.002) for _ in range(4)])
    g3 = lays["3x3"]
    put("area_3x3", [read(g3, [disk(g3)]) for _ in range(6)])
    put("corner_4x4", [read(g4, [disk(g4, off=0.019)]) for _ in range(6)])
    put("no_model_error_4x4", [read(g4, [disk(g4)], gain=0.03) for _ in range(6)])
    put("frames_4x4", [read(g4, [disk(g4)]) for _ in range(3)]
        + [read(g4, [disk(g4, f=(0.02, 0.4), off=0.019)]) for _ in range(2)] + [read(g4, [])], active=True)
    for name, gain in (("humanoid_own", 0.0), ("humanoid_gain", 0.03)):
        frames = []
        for _ in range(3):
            while True:
                picks = rng.choice(hum.n, 10, replace=False)
                at = hum.centres[picks]
                if min(float(np.hypot(*(at[i] - at[j]))) for i in range(10) for j in range(i + 1, 10)) > 3.5 * hum.side:
                    break
            frames.append(read(hum, [disk(hum, at=int(r), off=0.012) for r in picks], gain=gain))
        put(name, frames, active=True)
    np.savez_compressed(INPUTS, **inputs)  # type: ignore[arg-type]  # numpy's stub types **kwds as its allow_pickle flag
    with np.load(INPUTS) as stored:
        results = _run(dict(stored))
    RESULTS.write_text(json.dumps(results, indent=0, sort_keys=True) + "\n")
    for name, frames_ in results.items():
        print(name, [len(cs) for cs in frames_])


if __name__ == "__main__":  # pragma: no cover
    if sys.argv[1:] == ["--regenerate"]:
        _generate()
    else:
        print(__doc__)
