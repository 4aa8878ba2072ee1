"""Heartbeats of an event-based skin on mesh time go in each bridge's own slot.

Every bridge samples the same instants on mesh time; heartbeats timed only from the last
sample sent left all bridges of an idle skin in one frame once a second, a burst that
contended for the cells and taught the host delivery delays tens of milliseconds long
(which then held every skin frame back as long). Each bridge now sends its heartbeat in
its own slot of the heartbeat period (emulator/firmware/reporting.py).
"""

from __future__ import annotations

from collections import Counter

from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.reporting import Reporter, ReportingMode
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import VirtualMesh
from cellbridge.protocol import Data, Sample, SampleFlags, decode
from cobs import cobs
from hypothesis import given
from hypothesis import settings as hsettings
from hypothesis import strategies as st

PERIOD = 500_000  # 100 Hz at 50 MHz
CPM = 50_000


def _sent(phase: float, n: int, on_time: bool = True, changes: frozenset[int] = frozenset()) -> list[int]:
    """Indices a reporter sends of ``n`` samples at 100 Hz, heartbeat 1 s; ``changes``: indices
    whose reading moved beyond the threshold."""
    rep = Reporter(ReportingMode(40, 1000), cycles_per_ms=CPM, phase=phase)
    out = []
    c = 1000
    for k in range(n):
        if k in changes:
            c += 500
        if rep.wants(Sample(0, 7 + k * PERIOD, c, c, 0, k), PERIOD, on_time):
            out.append(k)
    return out


def test_a_bridge_sends_its_heartbeats_in_its_slot() -> None:
    sent = _sent(0.37, 1000)
    assert sent[0] == 0  # the first sample: the host's reference
    beats = sent[1:]
    assert len(beats) == 10 and all(k % 100 == 37 for k in beats), beats
    assert all(b - a <= 100 for a, b in zip(sent, sent[1:]))  # never more than a heartbeat apart


def test_two_bridges_with_different_slots_never_beat_in_one_frame() -> None:
    a, b = set(_sent(0.10, 1000)[2:]), set(_sent(0.60, 1000)[2:])
    assert a and b and not a & b


def test_off_mesh_time_the_heartbeat_is_one_heartbeat_after_the_last_sample_sent() -> None:
    assert _sent(0.37, 450, on_time=False) == [0, 100, 200, 300, 400]


@hsettings(max_examples=60, deadline=None)
@given(st.floats(0.0, 0.999), st.frozensets(st.integers(1, 1500), max_size=20))
def test_heartbeats_are_never_more_than_a_heartbeat_apart_and_return_to_the_slot(phase, changes) -> None:
    sent = _sent(phase, 2000, changes=changes)
    assert all(b - a <= 100 for a, b in zip(sent, sent[1:]))
    # after the last change and the sample that follows it, every heartbeat is in the slot
    last = max(changes, default=0)
    tail = [k for k in sent if k > last + 1]
    assert tail and all(k % 100 == int(phase * 100) for k in tail), (tail, int(phase * 100))


def test_an_idle_event_based_skin_spreads_its_heartbeats_over_the_frames() -> None:
    """A 4x4 idle skin on mesh time: no frame index carries the heartbeats of more than two
    bridges (before the slots, every bridge's heartbeat shared one index)."""
    mesh = meshgen.grid(4, 4, gateways=(1,))
    vm = VirtualMesh(mesh, seed=3, random_epochs=True, readout=False,  # DATA heartbeats (unscheduled path)
                     settings=Settings(rate_hz=100, reporting=ReportingMode(40, 1000)))
    vm.run(14.0)
    per_index: Counter[int] = Counter()
    for segment in bytes(vm.serial[mesh.gateways[0]]).split(b"\x00"):
        if not segment:
            continue
        try:
            frame = decode(cobs.decode(segment))
        except Exception:  # a partial frame at the end of the run
            continue
        if isinstance(frame.payload, Data):
            for s in frame.payload.samples:
                if not s.flags & SampleFlags.NO_MESH_TIME:
                    per_index[s.index] += 1
    late = max(per_index) - 600  # the last 6 s: routes, mesh time and first samples behind
    per_index = Counter({k: v for k, v in per_index.items() if k >= late})
    assert max(per_index.values()) <= 2, per_index.most_common(3)
    assert len(per_index) >= 16 * 5, len(per_index)  # every bridge beat every second
