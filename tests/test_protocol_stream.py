"""Serial framing: any chunking, any corruption: exactly the intact frames, the rest counted."""

from __future__ import annotations

import tracemalloc
from typing import Any

from cellbridge.protocol import Beacon, Frame, StreamDecoder, encode, encode_stream
from cellbridge.protocol.stream import max_encoded_len
from cobs import cobs
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from support.protocol_strategies import simple_frames

sendable = simple_frames.filter(lambda f: len(_raw_len(f)) <= 255)


def _raw_len(frame: Frame) -> bytes:
    try:
        return encode(frame)
    except Exception:
        return b"x" * 999


def _feed_in_chunks(decoder: StreamDecoder, stream: bytes, cuts: list[int]) -> list[Frame]:
    out: list[Frame] = []
    bounds = [0, *sorted(c % (len(stream) + 1) for c in cuts), len(stream)]
    for a, b in zip(bounds, bounds[1:]):
        out += decoder.feed(stream[a:b])
        assert decoder.buffered <= decoder.max_buffer
    return out


@settings(max_examples=150, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(
    frames=st.lists(sendable, min_size=1, max_size=12),
    damage=st.lists(st.tuples(st.integers(0, 10**6), st.sampled_from(["flip", "insert"]),
                              st.binary(min_size=1, max_size=6)), max_size=6),
    cuts=st.lists(st.integers(0, 10**6), max_size=20),
    one_byte_at_a_time=st.booleans(),
)
def test_stream_yields_exactly_the_intact_frames(frames, damage, cuts, one_byte_at_a_time) -> None:
    data = bytearray(b"".join(encode_stream(f) for f in frames))
    for pos, kind, junk in damage:
        pos %= len(data)
        if kind == "flip":
            data[pos] ^= junk[0] or 0x5A
        else:
            data[pos:pos] = junk
    stream = bytes(data)
    # Oracle: a frame is intact when its exact encoding still stands between two delimiters.
    segments = stream.split(b"\x00")
    by_encoding = {cobs.encode(encode(f)): f for f in frames}
    expected = [by_encoding[s] for s in segments if s in by_encoding]
    garbage = [s for s in segments if s and s not in by_encoding]

    decoder = StreamDecoder()
    if one_byte_at_a_time:
        got = [f for i in range(len(stream)) for f in decoder.feed(stream[i:i + 1])]
    else:
        got = _feed_in_chunks(decoder, stream, cuts)
    got += decoder.feed(b"\x00")  # close the last segment

    assert got == expected
    assert decoder.frames_ok == len(expected)
    assert sum(decoder.frames_dropped.values()) == len(garbage)
    delimiters = stream.count(0) + 1
    assert decoder.bytes_in == len(stream) + 1
    assert decoder.bytes_ok + sum(decoder.bytes_dropped.values()) + delimiters + decoder.buffered == decoder.bytes_in


def test_overlong_garbage_is_skipped_to_the_next_delimiter() -> None:
    frame = Frame(5, 0, 5, 9, Beacon(0, 10, 1))
    decoder = StreamDecoder()
    junk = bytes([0x41]) * 5000
    out = []
    for i in range(0, len(junk), 7):  # long run without delimiter arrives in small pieces
        out += decoder.feed(junk[i:i + 7])
        assert decoder.buffered <= decoder.max_buffer
    out += decoder.feed(encode_stream(frame))
    assert out == [frame]
    assert decoder.frames_dropped == {"overlong": 1}
    assert decoder.bytes_dropped["overlong"] == len(junk)


def test_cobs_and_crc_errors_are_counted_by_cause() -> None:
    good = encode_stream(Frame(5, 0, 5, 9, Beacon(0, 10, 1)))
    bad_crc = bytearray(cobs.encode(encode(Frame(5, 0, 5, 10, Beacon(0, 10, 1)))))
    bad_crc[-1] ^= 0x01 if bad_crc[-1] != 0x01 else 0x03
    decoder = StreamDecoder()
    out = decoder.feed(good + b"\x05ab\x00" + bytes(bad_crc) + b"\x00" + b"\x01\x00" + good)
    assert len(out) == 2
    assert decoder.frames_dropped["cobs"] == 1
    assert decoder.frames_dropped["crc"] == 1
    assert decoder.frames_dropped["short"] == 1  # b"\x01" decodes to an empty frame


def test_max_encoded_len_bounds_cobs() -> None:
    for n in (0, 1, 253, 254, 255, 600):
        for data in (bytes(n), b"\xff" * n, bytes(range(256))[:n]):
            assert len(cobs.encode(data)) <= max_encoded_len(n)


def test_feed_iter_yields_what_feed_returns_without_holding_it() -> None:
    frames = [Frame(7, 0, 7, i & 0xFFFF, Beacon(1, 20, 2)) for i in range(40_000)]
    stream = b"".join(encode_stream(f) for f in frames) + b"\x05ab"  # ~1 MB, many windows, a partial tail
    a, b = StreamDecoder(), StreamDecoder()
    assert list(b.feed_iter(stream)) == a.feed(stream) == frames
    assert a.counters() == b.counters() and a.buffered == 3
    c = StreamDecoder()
    tracemalloc.start()
    try:
        count = sum(1 for _ in c.feed_iter(stream))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert count == len(frames)
    assert peak < 2_000_000  # feed holds ~8 MB here: the 40 000 frames in its list


def test_a_memoryview_of_wide_items_is_counted_in_bytes() -> None:
    """bytes_in counts bytes, whatever the item size of the view fed (the accounting identity holds)."""
    import array

    frame = encode_stream(Frame(5, 0, 5, 9, Beacon(0, 10, 1)))
    words = array.array("H", frame + b"\x00" * (len(frame) % 2))  # the stream in 16-bit words
    d = StreamDecoder()
    assert len(d.feed(memoryview(words))) == 1
    c: dict[str, Any] = d.counters()  # nested counts, read as the test knows them
    assert c["bytes_in"] == len(words) * 2
    assert c["bytes_in"] == c["bytes_ok"] + sum(c["bytes_dropped"].values()) + c["delimiters"] + c["buffered"]


def test_frames_a_consumer_leaves_in_feed_iter_are_counted_not_lost() -> None:
    """A consumer that stops early (a handler raised, a break) leaves frames and bytes it
    never took: they are counted ``abandoned``, never as delivered, and the decoder
    resumes at the next delimiter of the next chunk."""
    frames = [Frame(7, 0, 7, i & 0xFFFF, Beacon(1, 20, 2)) for i in range(10_000)]  # ~230 KB: several windows
    stream = b"".join(encode_stream(f) for f in frames)
    d = StreamDecoder()
    taken = []
    for f in d.feed_iter(stream):
        taken.append(f)
        if len(taken) == 5:
            break
    c: dict[str, Any] = d.counters()
    # Decoded and not taken: frames abandoned; never read (later windows): bytes abandoned.
    assert c["frames_ok"] == 5 and 0 < c["frames_dropped"]["abandoned"] < len(frames) - 5
    assert c["bytes_ok"] == 5 * len(encode_stream(frames[0])[1:-1]) and c["bytes_dropped"]["abandoned"] > 0
    assert c["bytes_in"] == len(stream)
    assert c["bytes_in"] == c["bytes_ok"] + sum(c["bytes_dropped"].values()) + c["delimiters"] + c["buffered"]
    # The next chunk starts mid-frame (the rest of this one was never read): resynchronised.
    tail = encode_stream(frames[0])
    assert d.feed(tail[10:] + tail) == [frames[0]]
    after: dict[str, Any] = d.counters()
    assert after["bytes_in"] == after["bytes_ok"] + sum(after["bytes_dropped"].values()) + after["delimiters"] + after["buffered"]
