"""Ground truth of the scheduled readout, shared by its tests: what every bridge handed its
readout (logged as the sampler hands it over) and what the gateways' READOUT records say
of each element-frame."""

from __future__ import annotations

from typing import Any

import pytest
from cellbridge.emulator.firmware.firmware import Firmware
from cellbridge.emulator.firmware.readout import FrameReadout
from cellbridge.emulator.mesh.virtual import VirtualMesh
from cellbridge.protocol import FrameType, Readout, ReadoutSample, Sample

Truth = dict[tuple[int, int], tuple[int, int, bool]]  # (bridge, index) -> (c1, c2, sent as a sample)


def log_readout_states(monkeypatch: pytest.MonkeyPatch) -> Truth:
    """From now on every bridge's own state of every frame is logged in the returned dict
    (until ``monkeypatch`` undoes it): the reading its sampler took, and whether the
    bridge put it in its record as a sample (a change, periodic, a refresh, a new route;
    not when it had no route: it went nowhere)."""
    log: Truth = {}
    real = Firmware._readout_sample
    own = FrameReadout.own

    def logged(self: Firmware, s: Sample, kept: bool, start: int) -> None:
        log[(self.me, s.index)] = (s.c1, s.c2, False)
        real(self, s, kept, start)

    def put(self: FrameReadout, index: int, rate: int, mode: Any, oversampling: int, state: Any, slot: int,
            span: int, root: int = 0) -> None:
        if isinstance(state, ReadoutSample) and (self.me, index) in log:
            log[(self.me, index)] = (*log[(self.me, index)][:2], True)
        own(self, index, rate, mode, oversampling, state, slot, span, root)

    monkeypatch.setattr(Firmware, "_readout_sample", logged)
    monkeypatch.setattr(FrameReadout, "own", put)
    return log


def records(vm: VirtualMesh) -> dict[tuple[int, int], tuple[str, ReadoutSample | None]]:
    """(bridge, index) -> its state in the gateways' records (each element-frame once)."""
    out: dict[tuple[int, int], tuple[str, ReadoutSample | None]] = {}
    for frames in vm.frames.values():
        for f in frames:
            if f.type is FrameType.READOUT:
                r: Readout = f.payload  # type: ignore[assignment]  # a READOUT frame's payload
                for s in r.samples:
                    assert (s.bridge, r.index) not in out, "an element-frame in two records"
                    out[(s.bridge, r.index)] = ("s", s)
                for b in r.unchanged:
                    assert (b, r.index) not in out, "an element-frame in two records"
                    out[(b, r.index)] = ("u", None)
                for b in r.missing:
                    assert (b, r.index) not in out, "an element-frame in two records"
                    out[(b, r.index)] = ("m", None)
    return out


def check_known(got: dict[tuple[int, int], tuple[str, ReadoutSample | None]], truth: Truth,
                threshold: int = 40) -> int:
    """Every element-frame the gateways' records let the host know holds what its bridge
    sampled: a sample is the frame's reading or the last sample the bridge sent (an
    expansion, the gateway's refresh); an *unchanged* after a frame the host knew lies
    within ``threshold`` counts of the host's reading. Returns how many unchanged were
    checked so."""
    sent: dict[int, list[tuple[int, int, int]]] = {}  # bridge -> (index, c1, c2) of its samples sent
    for (b, k), (c1, c2, went) in sorted(truth.items(), key=lambda x: x[0][1]):
        if went:
            sent.setdefault(b, []).append((k, c1, c2))
    reading: dict[int, tuple[int, int]] = {}
    prev_known: dict[int, int] = {}
    unchanged = 0
    for (b, k) in sorted(got, key=lambda x: (x[1], x[0])):
        state, s = got[(b, k)]
        if state == "s":
            assert s is not None
            last_sent = [(c1, c2) for (j, c1, c2) in sent.get(b, []) if j <= k][-1:]
            assert (s.c1, s.c2) == truth[(b, k)][:2] or [(s.c1, s.c2)] == last_sent, (b, k)
            reading[b] = (s.c1, s.c2)
        elif state == "u" and prev_known.get(b) == k - 1 and b in reading:
            c1, c2, _ = truth[(b, k)]
            assert abs(c1 - reading[b][0]) <= threshold and abs(c2 - reading[b][1]) <= threshold, (
                b, k, (c1, c2), reading[b])
            unchanged += 1
        elif state != "u":
            reading.pop(b, None)
        prev_known[b] = k if state != "m" else -1
    return unchanged
