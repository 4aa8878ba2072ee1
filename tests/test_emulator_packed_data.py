"""The emulated firmware writes protocol version 3: packed DATA samples, frames filled to what fits.

Version 3 packs every sample after a frame's first into ~11 bytes (docs/protocol.md §4),
so a frame the firmware fills holds more samples than version 2's 8-12; the sampler's
room estimate must plan for that, and lazy sampling (samples computed when their frame
is due) must still send exactly what gate-by-gate sampling sends.
"""

from __future__ import annotations

from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, VirtualMesh
from cellbridge.protocol import MAX_FRAME, VERSION, Data, decode
from cobs import cobs

MS = CLOCK_HZ // 1000


def _data_frames(serial: bytes) -> list[tuple[bytes, Data, int]]:
    """(wire bytes, payload, origin) of every whole DATA frame on a gateway's serial line."""
    out = []
    for segment in serial.split(b"\x00"):
        if not segment:
            continue
        wire = cobs.decode(segment)
        frame = decode(wire)
        if isinstance(frame.payload, Data):
            out.append((wire, frame.payload, frame.origin))
    return out


def _run(lazy: bool) -> tuple[list[tuple[int, bytes]], bytes]:
    # Long batches (400 ms, up to 32 samples): frames fill by bytes, not by time. Timed
    # batches: an aligned one holds what the planner counts on at the widest (15 here).
    vm = VirtualMesh(meshgen.line(3), seed=4, random_epochs=True, lazy_sampling=lazy, batch_max=32, readout=False,
                     max_latency=400 * MS, aligned_batches=False)
    vm.run(4.0)
    return list(vm.serial_chunks[1]), bytes(vm.serial[1])


def test_the_firmware_fills_version_3_frames_with_packed_samples() -> None:
    chunks, serial = _run(lazy=True)
    frames = _data_frames(serial)
    assert frames and all(w[0] == VERSION == 4 for w, _, _ in frames)
    assert all(len(w) <= MAX_FRAME for w, _, _ in frames)
    assert all(d.period == CLOCK_HZ // d.rate == 500_000 for _, d, _ in frames)
    # full frames: 19 samples with a 64-bit first cycle (version 2 fitted 8 to 12)
    full = [d for _, d, _ in frames if len(d.samples) >= 17]
    assert len(full) >= len(frames) // 2, sorted(len(d.samples) for _, d, _ in frames)
    # the chips' cycle counters started far from 0 (random epochs): the first sample is wide,
    # the later ones still cost ~11 bytes
    assert any(d.samples[0].cycle >= 2**32 for d in full)
    # every bridge's samples arrive in order, no index lost between frames of one bridge
    for origin in {o for _, _, o in frames}:
        idx = [s.index for _, d, o in frames if o == origin for s in d.samples if not s.flags & 4]
        assert idx == sorted(idx) and len(set(idx)) == len(idx)


def test_lazy_sampling_sends_what_gate_by_gate_sampling_sends_when_frames_fill_by_bytes() -> None:
    """The room the sampler plans for (a frame's first sample at its widest, later ones
    packed) must not be more than fits: a lazy bridge would wake after its frame filled and
    send it late."""
    lazy, eager = _run(lazy=True), _run(lazy=False)
    assert lazy == eager
