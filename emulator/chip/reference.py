"""Deliberately naive per-cycle models of the counter and the ADC, for tests.

They step the chip clock one cycle at a time through flops, a counter register and a
SAR state machine, reading the oscillator's edges and the ADC's held value from the
same definitions the fast path uses (:class:`~cellbridge.emulator.chip.oscillator.EdgeTrain`,
:mod:`cellbridge.emulator.chip.adc`). Everything in between — synchroniser, edge detector,
16-bit register with wrap and sticky overflow, bit-by-bit approximation — is written
out as hardware would do it, so that the fast path's closed forms are checked against
something that cannot share their shortcuts. Slow by design (≈1 µs per cycle).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from cellbridge.emulator.chip.adc import AdcTiming
from cellbridge.emulator.chip.oscillator import SYNC_LATENCY, EdgeTrain

__all__ = ["CounterTrace", "ConversionTrace", "step_counter", "step_conversions"]


class CounterTrace(NamedTuple):
    register: int  #: counter register after the gate
    overflow: bool  #: sticky overflow flag
    events: list[int]  #: cycles (absolute) at which the register incremented


class ConversionTrace(NamedTuple):
    codes: list[int]  #: one code per conversion
    sample_cycles: list[int]  #: cycle at which each conversion held its input
    done_cycles: list[int]  #: cycle at which each conversion's last bit was decided
    cycles: int  #: cycles the whole run took


def step_counter(train: EdgeTrain, start_cycle: int, counter_bits: int = 16) -> CounterTrace:
    """Run the synchroniser and counter cycle by cycle over ``train``'s gate."""
    rises, falls = train.edges()
    rises_l, falls_l = rises.tolist(), falls.tolist()
    origin = start_cycle - SYNC_LATENCY
    mask = (1 << counter_bits) - 1
    flop1 = flop2 = flop2_before = 0
    register, overflow, events = 0, False, []
    k = -1  # index of the last rising edge at or before the current cycle
    first = math.floor(rises_l[0]) - 1  # output is low before the first edge: flops settled at 0
    for s in range(first, train.gate + SYNC_LATENCY):  # s: cycle relative to the origin
        while k + 1 < len(rises_l) and rises_l[k + 1] <= s:
            k += 1
        level = 1 if k >= 0 and s < falls_l[k] else 0
        increment = flop2 == 1 and flop2_before == 0  # edge detector, before the clock edge
        flop2_before, flop2, flop1 = flop2, flop1, level
        if increment and SYNC_LATENCY <= s < train.gate + SYNC_LATENCY:
            register = (register + 1) & mask
            if register == 0:
                overflow = True
            events.append(origin + s)
    return CounterTrace(register, overflow, events)


def step_conversions(
    timing: AdcTiming, held: np.ndarray, start_cycle: int, bits: int
) -> ConversionTrace:
    """Run ``len(held)`` charge-time conversions cycle by cycle from ``start_cycle``.

    ``held`` holds the sample-and-hold value of each conversion (from
    :func:`cellbridge.emulator.chip.adc.held_inputs`); the stepper decides when it is
    taken and approximates it one bit per cycle.
    """
    codes: list[int] = []
    samples: list[int] = []
    dones: list[int] = []
    cycle = start_cycle
    for x in held.tolist():
        for _ in range(timing.discharge):  # channel shorted
            cycle += 1
        for _ in range(timing.sample_delay):  # charging through R_adc
            cycle += 1
        samples.append(cycle)  # sample-and-hold closes at this cycle
        code = 0
        for bit in reversed(range(bits)):  # one comparison per cycle
            trial = code | (1 << bit)
            if x >= trial:
                code = trial
            if bit == 0:
                dones.append(cycle)
            cycle += 1
        codes.append(code)
    return ConversionTrace(codes, samples, dones, cycle - start_cycle)
