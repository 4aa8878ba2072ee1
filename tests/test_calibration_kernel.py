"""The calibrator's compiled step (cellbridge.tactile.calibration_kernel) against its numpy step:
the same outputs and the same state, bit for bit, step after step."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from cellbridge.tactile import calibration_kernel
from cellbridge.tactile.calibration import CalibrationConfig, Calibrator
from cellbridge.tactile.contact_surface import ContactSurface
from cellbridge.tactile.element import ElementParams

N = 60
#: Everything a step may change (Calibrator's per-element state and its skin-wide state).
STATE = (*Calibrator._PER_ELEMENT, "_common", "_spread", "_spread_age", "_anchor_age", "_common_jumps",
         "_catchups", "_last_jump", "_thr")


@pytest.fixture(scope="module", autouse=True)
def warm() -> None:
    calibration_kernel.warm_up()


def same(a: object, b: object) -> bool:
    """Equal bit for bit (arrays: dtype, shape and bytes; NaNs and signed zeros included)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.dtype == b.dtype
                and a.shape == b.shape and np.ascontiguousarray(a).tobytes() == np.ascontiguousarray(b).tobytes())
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


def scenario(seed: int, steps: int):
    """(t, readings) of a skin of N elements: noise and a slow common drift; presses that are
    contacts' readings (held past max_touch: kept); a press turning into one layer alone while
    touched (no contact's reading: re-baselined at max_touch); one layer drifting alone (no
    touch); elements below their baselines (followed fast); silences longer than tau (caught
    up); missing readings; a common step of the whole skin."""
    rng = np.random.default_rng(seed)
    base = 10e-12 + rng.normal(size=(N, 2)) * 1e-14
    for k in range(steps):
        v = base + rng.normal(size=(N, 2)) * 1e-16 + k * 2e-19
        if (k // 100) % 3 == 1:
            v[:6] += 3e-13 * np.array([1.0, 0.6])
        if 200 <= k < 900:
            v[50:53] += 3e-13 * (np.array([1.0, 0.6]) if k < 300 else np.array([1.0, 0.0]))
        if (k // 150) % 4 == 2:
            v[10:14, 0] += 2e-13
        if (k // 170) % 5 == 3:
            v[20:23] -= 1.5e-13
        if 900 < k < 1300:
            v[40:45] = np.nan
        if 1300 <= k < 1320:
            v[40:45] += 5e-16
        if 2000 < k < 2050:
            v += 5e-13
        v[rng.random(N) < 0.2] = np.nan
        yield 0.01 * (k + 1), v


def _count_compiled(cal: Calibrator) -> list[int]:
    """``cal``'s steps that the compiled step took itself, counted in the list's one item."""
    count = [0]
    real = cal.update_compiled

    def counted(t0: float, v: np.ndarray):
        got = real(t0, v)
        count[0] += got is not None
        return got

    cal.update_compiled = counted  # type: ignore[method-assign]
    return count


def run_both(cfg: CalibrationConfig, surface: bool, steps: int = 2600, seed: int = 0) -> tuple[Calibrator, int]:
    """Both steps side by side on :func:`scenario`; asserts they agree every step. Returns the
    numpy calibrator and how many steps the compiled one took itself."""
    def make(compiled: bool) -> Calibrator:
        return Calibrator(N, 2, cfg, is_contact=ContactSurface(ElementParams(), 2e-15) if surface else None,
                          compiled=compiled)

    a, b = make(False), make(True)
    compiled = _count_compiled(b)
    for k, (t, v) in enumerate(scenario(seed, steps)):
        if k == 1400:
            a.tare([1, 2, 3])
            b.tare([1, 2, 3])
        ra, rb = a.update(t, v.copy()), b.update(t, v.copy())
        for f in ra._fields:
            assert same(getattr(ra, f), getattr(rb, f)), (k, f)
        for name in STATE:
            assert same(getattr(a, name), getattr(b, name)), (k, name)
    return a, compiled[0]


def test_compiled_step_is_the_numpy_step_with_contact_surface() -> None:
    cfg = CalibrationConfig(n_baseline=5, max_touch=3.0, holdoff=0.5, tau=2.0)
    a, ran = run_both(cfg, surface=True)
    h: dict[str, Any] = a.health()
    # the scenario took every rule's rare branch, so the comparison covered them
    assert h["rebaselines_total"] > 0 and h["holds_total"] > 0
    assert h["common_jumps"] > 0 and h["outage_catchups"] > 0
    assert ran > 2000  # all but the collecting steps were the kernel's


def test_compiled_step_is_the_numpy_step_without_contact_test_or_common_mode() -> None:
    cfg = CalibrationConfig(n_baseline=5, max_touch=3.0, holdoff=0.5, tau=2.0, common_mode=False)
    a, ran = run_both(cfg, surface=False, steps=1500, seed=1)
    h: dict[str, Any] = a.health()
    assert h["rebaselines_total"] > 0
    assert ran > 1200
    cfg = CalibrationConfig(n_baseline=5, max_touch=None, min_common=3, common_spread=float("inf"))
    _, ran = run_both(cfg, surface=True, steps=1500, seed=2)
    assert ran > 1200
    cfg = CalibrationConfig(n_baseline=5, tau=float("inf"), tau_negative=0.5, max_touch=3.0)  # a frozen baseline
    _, ran = run_both(cfg, surface=True, steps=1500, seed=3)
    assert ran > 1200


def test_a_step_the_kernel_was_not_compiled_for_is_numpys() -> None:
    """Read-only readings are another argument type: the warm kernel compiles nothing more
    (seconds in the middle of a frame) and the numpy step takes them, with the same result."""
    a, b = (Calibrator(4, 2, CalibrationConfig(n_baseline=1), compiled=c) for c in (False, True))
    v = np.full((4, 2), 1e-11)
    a.update(0.0, v)
    b.update(0.0, v)
    v = v + 1e-13
    v.setflags(write=False)
    assert b.update_compiled(0.01, v) is None
    ra, rb = a.update(0.01, v), b.update(0.01, v)
    assert all(same(getattr(ra, f), getattr(rb, f)) for f in ra._fields)


def test_the_numpy_step_raises_what_it_raises() -> None:
    """Time going backwards is refused as before (the kernel leaves such a step untouched)."""
    cal = Calibrator(4, 2, CalibrationConfig(n_baseline=1), compiled=True)
    cal.update(1.0, np.full((4, 2), 1e-11))
    cal.update(1.01, np.full((4, 2), 1e-11))
    with pytest.raises(ValueError, match="backwards"):
        cal.update(0.5, np.full((4, 2), 1e-11))


def test_a_common_jump_in_an_anchoring_step_records_the_jump_alone() -> None:
    """The jump's record (health()["last_common_jump"]) is the offset's change by the jump: in a
    step that also anchors the offset, the anchor's shift is not part of it (as in the numpy step)."""
    cfg = CalibrationConfig(n_baseline=1, max_touch=None)
    a, b = (Calibrator(8, 2, cfg, compiled=c) for c in (False, True))
    rng = np.random.default_rng(5)
    base = 1e-11 + rng.normal(size=(8, 2)) * 1e-14
    for k in range(26):
        v = base + rng.normal(size=(8, 2)) * 1e-16 + k * 1e-17
        if k >= 25:  # the step of the jump is one of the anchor's (every 8th)
            v = v + 5e-13
        a.update(0.01 * k, v.copy())
        b.update(0.01 * k, v.copy())
    assert a._last_jump is not None and a._last_jump["t"] == 0.25
    assert same(a._last_jump, b._last_jump)
    assert same(a._common, b._common)


def test_the_kernel_warm_mid_press_takes_over_with_the_same_numbers(monkeypatch: pytest.MonkeyPatch) -> None:
    """A daemon's first frames are numpy's until the warm-up (two threads at once here) ends,
    in the middle of a press: every step, before and after, is the numpy step's."""
    import threading

    monkeypatch.setattr(calibration_kernel, "READY", False)
    cfg = CalibrationConfig(n_baseline=3, max_touch=2.0, holdoff=0.2, tau=1.0)
    a, b = (Calibrator(N, 2, cfg, is_contact=ContactSurface(ElementParams(), 2e-15), compiled=c) for c in (False, True))
    compiled = _count_compiled(b)
    errors: list[BaseException] = []

    def warm() -> None:
        try:
            calibration_kernel.warm_up()
        except BaseException as exc:  # (asserted below)
            errors.append(exc)

    for k, (t, v) in enumerate(scenario(7, 700)):
        if k == 150:  # inside a press of elements 0..5 (steps 100..199, and 400..499)
            assert compiled[0] == 0 and a.touched[:6].any()
            threads = [threading.Thread(target=warm) for _ in range(2)]
            for th in threads:
                th.start()
            for th in threads:
                th.join()
            assert not errors and calibration_kernel.READY
        ra, rb = a.update(t, v.copy()), b.update(t, v.copy())
        for f in ra._fields:
            assert same(getattr(ra, f), getattr(rb, f)), (k, f)
        for name in STATE:
            assert same(getattr(a, name), getattr(b, name)), (k, name)
    assert compiled[0] > 400


@pytest.mark.parametrize("shape", [(5, 2), (4, 3), (3, 2), (4, 1), (8,)])
def test_the_compiled_step_refuses_readings_of_another_shape(shape: tuple[int, ...]) -> None:
    """update_compiled is public: readings of another shape than (n_elements, n_channels) are
    refused as update refuses them, before the kernel (which indexes the calibrator's state by
    the readings' shape, unchecked: more rows or channels wrote past the state's arrays)."""
    cal = Calibrator(4, 2, CalibrationConfig(n_baseline=1), compiled=True)
    cal.update(0.0, np.full((4, 2), 1e-11))
    before = {name: np.copy(getattr(cal, name)) for name in Calibrator._PER_ELEMENT}
    with pytest.raises(ValueError, match="shape"):
        cal.update_compiled(0.01, np.full(shape, 1e-11))
    for name, was in before.items():
        assert same(getattr(cal, name), was), name


def test_a_min_common_beyond_64_bits_is_stepped_as_numpy_steps_it() -> None:
    """min_common is any integer >= 1 (one larger than the skin: never a common offset); one past
    the kernel's 64-bit integers raised OverflowError from every step instead of stepping."""
    cfg = CalibrationConfig(n_baseline=1, min_common=10**20)
    a, b = (Calibrator(4, 2, cfg, compiled=c) for c in (False, True))
    for k in range(4):
        v = np.full((4, 2), 1e-11) + k * 1e-13
        ra = a.update(0.01 * k, v.copy())
        rb = b.update(0.01 * k, v.copy()) if k == 0 else b.update_compiled(0.01 * k, v.copy())  # (0: collecting)
        assert rb is not None and all(same(getattr(ra, f), getattr(rb, f)) for f in ra._fields), k
        for name in STATE:
            assert same(getattr(a, name), getattr(b, name)), (k, name)
