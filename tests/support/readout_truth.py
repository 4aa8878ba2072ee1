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
