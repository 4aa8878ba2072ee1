"""One frame, one byte string: decode accepts exactly the canonical msgpack encoding.

A test-only encoder writes each value in any form msgpack allows (wider ints, longer
array/str/bin headers, float32); decode must accept the result exactly when every
choice was the smallest form, and then ``encode(decode(x)) == x``.
"""

from __future__ import annotations

import struct

import msgpack
import pytest
from cellbridge.protocol import MAX_FRAME, Frame, FrameType, ProtocolError, decode, encode
from cellbridge.protocol.frame import CRC_LEN, HEADER_LEN
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from support.protocol_strategies import frames_of, messages_by_type
from support.protocol_wire import sealed


def _int_forms(n: int) -> list[bytes]:
    forms = []
    if -32 <= n < 0x80:  # positive fixint, or negative fixint (version 3's packed samples)
        forms.append(bytes([n & 0xFF]))
    for code, fmt, lo, hi in ((0xCC, ">B", 0, 0xFF), (0xCD, ">H", 0, 0xFFFF), (0xCE, ">I", 0, 2**32 - 1),
                              (0xCF, ">Q", 0, 2**64 - 1), (0xD0, ">b", -128, 127), (0xD1, ">h", -2**15, 2**15 - 1),
                              (0xD2, ">i", -2**31, 2**31 - 1), (0xD3, ">q", -2**63, 2**63 - 1)):
        if lo <= n <= hi:
            forms.append(bytes([code]) + struct.pack(fmt, n))
    return forms


def _sized_forms(n: int, fix: int | None, fix_max: int, codes: tuple[int, ...]) -> list[bytes]:
    forms = [bytes([fix | n])] if fix is not None and n <= fix_max else []
    for code, fmt, hi in zip(codes, (">B", ">H", ">I"), (0xFF, 0xFFFF, 2**32 - 1)):
        if code and n <= hi:
            forms.append(bytes([code]) + struct.pack(fmt, n))
    return forms


def sloppy(obj: object, pick) -> bytes:
    """``obj`` in msgpack, each header chosen by ``pick(forms)`` (index 0 is the canonical form)."""
    if obj is None or obj is True or obj is False:
        return msgpack.packb(obj)
    if isinstance(obj, int):
        return pick(_int_forms(obj))
    if isinstance(obj, float):
        return pick([b"\xcb" + struct.pack(">d", obj), b"\xca" + struct.pack(">f", obj)]
                    if abs(obj) < 3e38 else [b"\xcb" + struct.pack(">d", obj)])
    if isinstance(obj, str):
        raw = obj.encode()
        return pick(_sized_forms(len(raw), 0xA0, 31, (0xD9, 0xDA, 0xDB))) + raw
    if isinstance(obj, bytes):
        return pick(_sized_forms(len(obj), None, 0, (0xC4, 0xC5, 0xC6))) + obj
    if isinstance(obj, list):
        return pick(_sized_forms(len(obj), 0x90, 15, (0, 0xDC, 0xDD))) + b"".join(sloppy(v, pick) for v in obj)
    raise TypeError(type(obj))


def _frames_of_every_type():
    return st.sampled_from(list(FrameType)).flatmap(
        lambda t: frames_of(messages_by_type[t]))


@settings(max_examples=400, suppress_health_check=[HealthCheck.too_slow])
@given(frame=_frames_of_every_type(), data=st.data())
def test_only_the_canonical_encoding_is_accepted(frame: Frame, data: st.DataObject) -> None:
    try:
        wire = encode(frame)
    except ProtocolError:
        return  # too large for one frame: nothing to decode
    chosen: list[int] = []

    def pick(forms: list[bytes]) -> bytes:
        i = data.draw(st.integers(0, len(forms) - 1) if len(forms) > 1 else st.just(0))
        chosen.append(i)
        return forms[i]

    obj = msgpack.unpackb(wire[HEADER_LEN:-CRC_LEN])
    body = wire[:HEADER_LEN] + sloppy(obj, pick)
    x = sealed(body)
    canonical = not any(chosen)
    assert (x == wire) == canonical
    if canonical:
        assert encode(decode(x)) == x
    else:
        with pytest.raises(ProtocolError) as err:
            decode(x)
        assert err.value.cause == ("too_large" if len(x) > MAX_FRAME else "payload")


@pytest.mark.parametrize("ftype", list(FrameType), ids=lambda t: t.name)
@settings(max_examples=40, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_canonical_round_trip_every_type(ftype: FrameType, data: st.DataObject) -> None:
    frame = data.draw(frames_of(messages_by_type[ftype]))
    try:
        wire = encode(frame)
    except ProtocolError:
        return
    assert encode(decode(wire)) == wire
    # the payload is what the reference msgpack packer writes for the wire object
    assert wire[HEADER_LEN:-CRC_LEN] == msgpack.packb(msgpack.unpackb(wire[HEADER_LEN:-CRC_LEN]))
