"""Health's per-bridge ``loss`` counts only frames the host should have received.

The virtual mesh's gateway bytes, at their virtual times, into the daemon's pipeline
(the two sans-I/O cores joined in memory). Bridges number the frames for the host
(DATA, HELLO, STATUS, CMD_REPLY) in one sequence and the frames that end at the next
hop (BEACON, LINK_ACK, BUNDLE) in another, so a gap the host sees is a frame lost: a
gateway bridge that delivered every sample showed ``loss`` ~0.93 while its link acks and
beacons took numbers from the same counter.
"""

from __future__ import annotations

import random
from collections import Counter

import pytest
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import CLOCK_HZ, VirtualMesh
from cellbridge.protocol import StreamDecoder, encode_stream

SECONDS = 6.0


@pytest.fixture(scope="module")
def reads() -> list[tuple[float, bytes]]:
    mesh = meshgen.grid(3, 3, gateways=(1,))
    vm = VirtualMesh(mesh, seed=2, random_epochs=True, readout=False)  # loss of DATA frames, by their numbering
    vm.run(SECONDS)
    assert vm.result().total("forwarded") > 0 and vm.result().total("beacons") > 0  # a multi-hop mesh at work
    return [(t / CLOCK_HZ, data) for t, data in vm.serial_chunks[1]]


def _health(chunks: list[tuple[float, bytes]]) -> dict[str, dict]:
    p = Pipeline(parse_config({"link": [{"name": "gw", "url": "/dev/null"}]}))
    for t, data in chunks:
        p.feed("gw", data, 100.0 + t)
    return p.health_body(100.0 + SECONDS)["bridges"]


def test_loss_is_zero_when_every_frame_arrives(reads) -> None:
    bridges = _health(reads)
    assert len(bridges) == 9
    for b, h in bridges.items():
        assert h["frames"] > 50 and h["samples"] > 300, b
        assert h["lost"] == 0 and h["loss"] == 0.0, (b, h["lost"], h["loss"])


def test_loss_is_the_share_of_frames_dropped_on_the_line(reads) -> None:
    # Drop whole frames on the serial line, each with probability 0.1 (deterministic):
    # every bridge's loss is the share of its frames dropped, as counted here.
    rng = random.Random(5)
    sent: Counter[int] = Counter()
    dropped: Counter[int] = Counter()
    last_kept: dict[int, int] = {}
    kept_chunks = []
    dec = StreamDecoder()
    n = 0
    for t, data in reads:
        out = bytearray()
        for f in dec.feed(data):
            n += 1
            if rng.random() < 0.1 and n > 20:  # the first frames (HELLOs) always pass
                dropped[f.origin] += 1
                sent[f.origin] += 1
                continue
            sent[f.origin] += 1
            last_kept[f.origin] = sent[f.origin]
            out += encode_stream(f)
        kept_chunks.append((t, bytes(out)))
    bridges = _health(kept_chunks)
    assert sum(dropped.values()) > 100
    for b, h in bridges.items():
        o = int(b)
        # gaps after a bridge's last delivered frame are not seen yet: count up to it
        tail = sent[o] - last_kept[o]
        true = (dropped[o] - tail) / (sent[o] - tail)
        assert h["lost"] == dropped[o] - tail, (b, h["lost"], dropped[o], tail)
        assert h["loss"] == pytest.approx(true, abs=1e-9), (b, h["loss"], true)
        assert 0.02 < h["loss"] < 0.3, (b, h["loss"])  # about the 10 % dropped, for every bridge
