"""Whatever arrives on a link, the pipeline counts it and goes on: it never raises."""

from __future__ import annotations

import math

from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.protocol import Data, Frame, Hello, Mode, Sample, encode_stream
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon_traffic import GridFrames
from support.pipeline_helpers import published, worker

CFG = parse_config({"link": [{"name": "gw", "url": "/dev/null"}], "calibration": {"n_baseline": 2}})
U64 = 2**64 - 1

samples = st.builds(
    Sample,
    element=st.integers(0, 3),
    cycle=st.one_of(st.integers(0, U64), st.integers(0, 10**9)),
    c1=st.integers(0, 2**32 - 1),
    c2=st.integers(0, 2**32 - 1),
    flags=st.integers(0, 255),
    index=st.one_of(st.integers(0, U64), st.integers(0, 10**6)),
)
data_frames = st.builds(
    lambda origin, seq, mode, over, ss, rate: Frame(1, 0, origin, seq, Data(mode, tuple(ss), over, rate)),
    origin=st.integers(1, 6),
    seq=st.integers(0, 0xFFFF),
    mode=st.sampled_from(list(Mode)),
    over=st.integers(1, 0xFFFF),
    ss=st.lists(samples, min_size=1, max_size=8),
    rate=st.integers(0, 0xFFFF),
)


def _pipeline() -> Pipeline:
    p = Pipeline(CFG)
    p.feed("gw", GridFrames().hellos(), 1000.0)
    return p


@settings(max_examples=150, deadline=None)
@given(frames=st.lists(data_frames, min_size=1, max_size=12), noise=st.binary(max_size=64),
       dt=st.floats(-5.0, 5.0))
def test_any_data_frames_and_noise_never_raise(frames: list[Frame], noise: bytes, dt: float) -> None:
    p = _pipeline()
    t = 1000.0
    for f in frames:
        t += dt  # host time may even go backwards (a clock step)
        for topic, msg in published(p.feed("gw", noise + encode_stream(f), t)):
            assert msg["v"] == 2
            if topic == "element":
                assert all(isinstance(x, float) for x in msg["c1"])
    h = published(p.tick(t + 10.0, force=True))
    assert h and h[0][0] == "health"
    job = p.contact_job()
    if job is not None:
        for c in worker().estimate_now(job):
            assert math.isfinite(c["x"]) or not c["valid"]


@settings(max_examples=100, deadline=None)
@given(blob=st.binary(max_size=600))
def test_random_bytes_are_counted(blob: bytes) -> None:
    p = _pipeline()
    p.feed("gw", blob, 1001.0)
    link = p.health_body(1001.0)["links"]["gw"]
    assert link["bytes"] >= len(blob)


@settings(max_examples=50, deadline=None)
@given(x=st.floats(-1.0, 1.0), y=st.floats(-1.0, 1.0), side=st.floats(0.001, 0.2), bridge=st.integers(1, 8))
def test_any_hello_geometry_is_placed_or_rejected(x: float, y: float, side: float, bridge: int) -> None:
    p = _pipeline()
    p.feed("gw", encode_stream(Frame(1, 0, bridge, 500, Hello(bridge, "x", x, y, side, 50_000_000, 3))), 1000.5)
    layout = p.health_body(1000.5)["layout"]
    placed = set(p.skin.layout.ids.tolist()) if p.skin.layout is not None else set()
    assert bridge in placed or bridge in layout["rejected"]
