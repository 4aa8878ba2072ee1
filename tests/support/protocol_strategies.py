"""Hypothesis strategies for every protocol message and frame (shared by the protocol tests)."""

from __future__ import annotations

from cellbridge.protocol import (
    Beacon,
    BridgeStatus,
    Bundle,
    Command,
    CommandReply,
    Data,
    Frame,
    FrameType,
    Hello,
    LinkAck,
    MeshTime,
    Mode,
    Neighbour,
    Op,
    Readout,
    ReadoutSame,
    ReadoutSample,
    Sample,
    Status,
)
from hypothesis import strategies as st

u8 = st.integers(0, 0xFF)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFF_FFFF)
u64 = st.integers(0, 0xFFFF_FFFF_FFFF_FFFF)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)

def _samples(limit: int) -> st.SearchStrategy[tuple[Sample, ...]]:
    code = st.integers(0, limit)
    return st.lists(st.builds(Sample, u16, u64, code, code, u8, u64), max_size=8).map(tuple)


# Counter mode: 16-bit counts, oversampling 1; ADC mode: sums of `oversampling` 8-bit codes.
# The period (version 3) only changes how the samples pack: any u32 with any samples.
counter_data = st.builds(Data, st.just(Mode.COUNTER), _samples(0xFFFF), st.just(1), u16, u32)
adc_data = st.integers(1, 0xFFFF).flatmap(
    lambda over: st.builds(Data, st.just(Mode.ADC), _samples(255 * over), st.just(over), u16, u32))
data = counter_data | adc_data
beacon = st.builds(Beacon, u16, u16, u8, st.none() | st.builds(MeshTime, u16, u16, u64))
hello = st.builds(Hello, u16, st.text(max_size=8), finite, finite,
                  st.floats(min_value=1e-3, max_value=1.0), u32, u32, u32)
status = st.builds(BridgeStatus, u16, u16, st.lists(st.builds(Neighbour, u16, u16), max_size=6).map(tuple),
                   u32, u32, u32, u64)
value = st.none() | u64
command = st.builds(Command, u16, st.sampled_from(Op), value)
reply = st.builds(CommandReply, u16, st.sampled_from(Op), st.sampled_from(Status), value)
link_ack = st.builds(LinkAck, u16, u16)

#: Bridge ids at the edges of msgpack's integer forms (fixint, uint8, uint16) and anywhere.
bridge_id = st.sampled_from([0, 1, 127, 128, 255, 256, 0xFFFE, 0xFFFF]) | u16


@st.composite
def readouts(draw: st.DrawFn, max_elements: int = 24) -> Readout:
    """A valid READOUT (version 4): distinct bridges, each in one state, every list increasing
    by bridge id; samples in the mode's ranges with overflow flags only; any index, rate,
    span, part of parts, root, age and step back to its reference (0: not said)."""
    mode = draw(st.sampled_from(Mode))
    over = 1 if mode is Mode.COUNTER else draw(st.integers(1, 0xFFFF))
    code = st.integers(0, 0xFFFF if mode is Mode.COUNTER else 255 * over)
    ids = sorted(draw(st.lists(bridge_id, unique=True, max_size=max_elements)))
    states = [draw(st.sampled_from("sum")) for _ in ids]
    samples = tuple(ReadoutSample(b, draw(code), draw(code), draw(st.integers(0, 3)))
                    for b, s in zip(ids, states) if s == "s")
    unchanged = tuple(b for b, s in zip(ids, states) if s == "u")
    missing = tuple(b for b, s in zip(ids, states) if s == "m")
    parts = draw(st.integers(1, 0xFF))
    return Readout(draw(u64), draw(st.integers(1, 0xFFFF)), mode, over, samples, unchanged, missing, draw(u32),
                   draw(st.integers(0, parts - 1)), parts, draw(st.integers(0, 0xFFFF)), draw(u32),
                   draw(st.integers(0, 127)))


readout = readouts()
#: a READOUT_SAME (version 4): any step and ref in their ranges
readout_same = st.builds(ReadoutSame, st.integers(1, 127), st.integers(0, 127))
#: the messages of versions 1 to 3 (READOUT and READOUT_SAME came with version 4)
simple_messages_v3 = data | beacon | hello | status | command | reply | link_ack
simple_messages = simple_messages_v3 | readout | readout_same

header = dict(src=u16, dst=u16, origin=u16, seq=u16, hops=u8, cost=u16, flags=st.integers(0, 0x0F))


def _consistent(frame: Frame) -> Frame:
    """A HELLO comes from the bridge it names (decode refuses the contradiction)."""
    if isinstance(frame.payload, Hello):
        frame.origin = frame.payload.bridge
    return frame


def frames_of(payloads: st.SearchStrategy) -> st.SearchStrategy[Frame]:
    """Frames with any header around ``payloads``, consistent where the payload names its origin."""
    return st.builds(Frame, payload=payloads, **header).map(_consistent)


def _bundles(inner: st.SearchStrategy[Frame]) -> st.SearchStrategy[Bundle]:
    return st.builds(Bundle, st.lists(inner.filter(lambda f: f.type.name != "HELLO"), min_size=1, max_size=3).map(tuple))


simple_frames = frames_of(simple_messages)
bundle = _bundles(simple_frames)
frames = simple_frames | st.builds(Frame, payload=bundle, **header)
#: frames an older version could carry too (no READOUT, also not inside a bundle): for the
#: tests that write them as version 1, 2 or 3
frames_v3 = frames_of(simple_messages_v3) | st.builds(Frame, payload=_bundles(frames_of(simple_messages_v3)), **header)

#: one payload strategy per frame type, so a test can prove it covers them all
messages_by_type = {
    FrameType.DATA: data, FrameType.BEACON: beacon, FrameType.HELLO: hello, FrameType.STATUS: status,
    FrameType.CMD: command, FrameType.CMD_REPLY: reply, FrameType.LINK_ACK: link_ack, FrameType.BUNDLE: bundle,
    FrameType.READOUT: readout, FrameType.READOUT_SAME: readout_same,
}
