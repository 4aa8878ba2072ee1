"""Speed of the chip model's fast path against the per-cycle reference, and the
chip's reading noise (what the tactile inverse's default noise is set from).

Run: .venv/bin/python bench/bench_chip.py   (one core, about 15 s)

Speed: one counter gate (default 100 000 cycles = 2 ms) and one ADC read, at the
element's rest capacitances; fast path best of several runs of many calls,
reference best of a few single calls. The mesh needs 64 bridges × 2 channels ×
100 Hz = 12 800 gates/s on one core, so the budget of one gate is 78 µs minus
everything else the mesh does: the target is ≤ 50 µs and a speed-up ≥ 1000×.

Noise: 1 000 readings of a fixed element per row, converted to capacitance the way
the host does (docs/emulator-chip.md).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from cellbridge.emulator.chip.chip import Chip  # noqa: E402
from cellbridge.emulator.chip.chip_noise import adc_noise, counter_noise  # noqa: E402
from cellbridge.emulator.chip.reference import step_conversions, step_counter  # noqa: E402
from cellbridge.tactile import DEFAULT_NOISE, ElementParams  # noqa: E402

from timing import best_rate, pin_to_one_core  # noqa: E402

FAST_CALLS = 2000
REPEATS = 5
MESH_GATES_PER_S = 64 * 2 * 100


def speed_rows(chip: Chip, caps: dict[str, float]) -> list[tuple[str, float, float]]:
    """(operation, fast µs per call, reference µs per call)."""
    rows = []
    gate = chip.config.gate_cycles
    for name, c in caps.items():
        starts = range(1000, 1000 + FAST_CALLS * gate, gate)

        def fast(c: float = c, starts: range = starts) -> None:
            for s in starts:
                chip.count(0, c, s, gate)

        def ref(c: float = c) -> None:
            step_counter(chip.edge_train(0, c, 1000, gate), 1000, chip.config.counter_bits)

        rows.append((f"counter gate, {name}", 1e6 / best_rate(fast, FAST_CALLS, REPEATS),
                     1e6 / best_rate(ref, 1, REPEATS)))
    c = caps["C1 rest"]
    timing = chip.config.adc_timing
    for n in (1, 16, 64):
        def fast_adc(n: int = n) -> None:
            for s in range(0, FAST_CALLS * 10_000, 10_000):
                chip.convert(0, c, s, n)

        def ref_adc(n: int = n) -> None:
            for s in range(0, 50 * 10_000, 10_000):
                step_conversions(timing, chip.held_inputs(0, c, s, n), s, chip.config.adc_bits)

        fast_adc()  # warm-up: the first ADC timings otherwise read high
        rows.append((f"ADC read, {n} conversion(s), C1 rest",
                     1e6 / best_rate(fast_adc, FAST_CALLS, REPEATS), 1e6 / best_rate(ref_adc, 50, REPEATS)))
    return rows


def main() -> int:
    pin_to_one_core()
    p = ElementParams()
    caps = {"C1 rest": p.C1_rest, "C2 rest": p.C2_rest}
    chip = Chip(seed=1)

    print(f"speed, one core (fast: best of {REPEATS} runs of {FAST_CALLS} calls)")
    print(f"  {'operation':<36} {'fast µs':>9} {'reference µs':>13} {'speed-up':>9}")
    rows = speed_rows(chip, caps)
    for name, fast, ref in rows:
        print(f"  {name:<36} {fast:>9.1f} {ref:>13.0f} {ref / fast:>8.0f}x")
    worst_gate = max(fast for name, fast, _ in rows if name.startswith("counter"))
    print(f"  mesh load: {MESH_GATES_PER_S:,} gates/s x {worst_gate:.1f} µs = "
          f"{MESH_GATES_PER_S * worst_gate * 1e-6:.0%} of one core")
    print("  target: counter gate <= 50 µs, speed-up >= 1000x (an ADC read is only 80 cycles per")
    print("  conversion, so its stepper is cheap and its speed-up small: listed for the cost per read)")
    print()

    print(f"noise of one reading at rest, jitter {chip.config.jitter:g}, "
          f"ADC input noise {chip.config.adc_noise_lsb:g} LSB (1000 readings each)")
    print(f"  {'reading':<30} {'channel':>8} {'mean':>10} {'rms':>8} {'rms fF':>8}")
    for ch, (name, c) in enumerate(caps.items()):
        f = counter_noise(chip, ch, c, readings=1000)
        print(f"  {'counter, 2 ms gate (counts)':<30} {name:>8} {f.mean:>10.2f} {f.rms:>8.3f} "
              f"{f.farads * 1e15:>8.3f}")
    for n in (1, 16, 64):
        for ch, (name, c) in enumerate(caps.items()):
            f = adc_noise(chip, ch, c, n, readings=1000)
            print(f"  {f'ADC, mean of {n} (codes)':<30} {name:>8} {f.mean:>10.2f} {f.rms:>8.3f} "
                  f"{f.farads * 1e15:>8.2f}")
    print(f"  tactile DEFAULT_NOISE (inverse's default, counter readings): {DEFAULT_NOISE * 1e15:g} fF")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
