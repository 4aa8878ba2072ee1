"""Protocol throughput on one core: encode, decode and serial stream decoding; DATA bytes per sample.

Run: ``.venv/bin/python bench/bench_protocol.py`` (or ``make bench``). The frame is
a DATA frame with one sample: the smallest frame a bridge sends, so the per-frame
cost dominates. Target: >= 200 000 decoded frames/s through the stream decoder.
A second DATA frame holds 5 samples of a periodic bridge 3 minutes after boot (the
reference firmware's frame at 100 Hz), so the per-sample cost of unpacking version 3's
packed samples shows too.

The next table is the wire cost of a DATA sample in protocol version 2 (every sample
absolute) and version 3 (samples after a frame's first packed: docs/protocol.md §4).

The last two are version 4's READOUT (docs/protocol.md §4): the bytes of one element in
each state by its bridge id, and the frames a gateway's record takes per skin frame.
"""

from __future__ import annotations

import msgpack
from cellbridge.protocol import (
    Data,
    Frame,
    HostReceiver,
    Mode,
    ProtocolError,
    Readout,
    ReadoutSample,
    Sample,
    StreamDecoder,
    decode,
    encode,
    encode_stream,
    fragment,
)

from timing import best_rate, pin_to_one_core

N = 200_000
TARGET_STREAM = 200_000
CLOCK_HZ = 50_000_000
RATE = 100
PERIOD = CLOCK_HZ // RATE


def periodic(n: int, cycle: int, index: int) -> tuple[Sample, ...]:
    """``n`` samples of a periodic bridge whose crystal drifts a few cycles per period."""
    out, c = [], cycle
    for i in range(n):
        out.append(Sample(0, c, 19_600 - i, 15_800 + i % 2, 0, index + i))
        c += PERIOD + (3, -2, 1, 0)[i % 4]
    return tuple(out)


def periodic_data(samples: tuple[Sample, ...]) -> Data:
    data = Data(Mode.COUNTER, samples, 1, RATE)
    if "period" in Data.__dataclass_fields__:  # protocol version 3
        data.period = PERIOD  # absent before version 3
    return data


def bytes_per_sample() -> None:
    """Wire bytes of a DATA sample, version 2 against what ``encode`` writes now."""
    print("\nDATA bytes per sample, counter mode, 100 Hz (msgpack of the sample; frame: header and CRC included)")
    print(f"{'cycle, index':<24} {'v2 sample':>10} {'now first':>10} {'now later':>10} "
          f"{'v2 frame of 5':>14} {'now frame of 5':>15} {'v2 B/sample':>12} {'now B/sample':>13}")
    for name, cycle, index in (("32-bit, 16-bit", 40_000_000, 4_000), ("64-bit, 16-bit", 9_000_000_123, 18_000),
                               ("64-bit, 32-bit", 40_000_000_000, 80_000)):
        samples = periodic(5, cycle, index)
        v2 = [len(msgpack.packb(list(s))) for s in samples]
        v2_frame = 16 + len(msgpack.packb([0, 1, [list(s) for s in samples], RATE]))
        now_frame = len(encode(Frame(7, 0, 7, 1, periodic_data(samples))))
        first = len(encode(Frame(7, 0, 7, 1, periodic_data(samples[:1]))))
        later = len(encode(Frame(7, 0, 7, 1, periodic_data(samples[:2])))) - first
        print(f"{name:<24} {v2[0]:>10} {v2[0]:>10} {later:>10} {v2_frame:>14} {now_frame:>15} "
              f"{v2_frame / 5:>12.1f} {now_frame / 5:>13.1f}")


def _readout_len(r: Readout) -> int:
    return len(encode(Frame(1, 0, 1, 7, r)))


def readout_bytes() -> None:
    """Wire bytes of a READOUT element in each state, and of whole records."""
    print("\nREADOUT bytes per element (msgpack of the entry), by bridge id")
    print(f"{'entry':<44} {'1-127':>6} {'128-255':>8} {'256-65534':>10}")
    base = Readout(2**20, RATE, Mode.COUNTER, 1, (), span_us=3000)
    rows = [("sample, counter mode (c1, c2 256-65535)", Mode.COUNTER, 1, 19_600, 15_800),
            ("sample, ADC mode x16 (c1, c2 256-4080)", Mode.ADC, 16, 2_272, 1_968),
            ("sample, ADC mode x1 (c1, c2 128-255)", Mode.ADC, 1, 200, 180),
            ("sample, ADC mode x1 (c1, c2 0-127)", Mode.ADC, 1, 100, 90)]
    for name, mode, over, c1, c2 in rows:
        empty = Readout(2**20, RATE, mode, over, (), span_us=3000)
        cost = [_readout_len(Readout(2**20, RATE, mode, over, (ReadoutSample(b, c1, c2),), span_us=3000))
                - _readout_len(empty) for b in (5, 200, 4000)]
        print(f"{name:<44} {cost[0]:>6} {cost[1]:>8} {cost[2]:>10}")
    cost = [_readout_len(Readout(2**20, RATE, Mode.COUNTER, 1, (), (b,), span_us=3000)) - _readout_len(base)
            for b in (5, 200, 4000)]
    print(f"{'unchanged or missing':<44} {cost[0]:>6} {cost[1]:>8} {cost[2]:>10}")

    print("\nREADOUT records per skin frame, counter mode, 100 Hz (index past 2^16, span_us 3000)")
    print(f"{'record':<48} {'payload B':>10} {'frames':>7} {'bytes on cell':>14} {'B/element':>10}")
    grid16, grid64 = range(1, 17), range(1, 65)
    records = [
        ("4x4 periodic", Readout(2**20, RATE, Mode.COUNTER, 1, tuple(ReadoutSample(b, 19_600, 15_800) for b in grid16),
                                 span_us=3000)),
        ("4x4 event-based, at rest", Readout(2**20, RATE, Mode.COUNTER, 1, (), tuple(grid16), span_us=3000)),
        ("4x4 event-based, one element moving", Readout(2**20, RATE, Mode.COUNTER, 1, (ReadoutSample(6, 21_000, 15_800),),
                                                        tuple(b for b in grid16 if b != 6), span_us=3000)),
        ("4x4 event-based, four presses (8 moving)", Readout(
            2**20, RATE, Mode.COUNTER, 1, tuple(ReadoutSample(b, 21_000, 15_800) for b in grid16 if b % 2),
            tuple(b for b in grid16 if not b % 2), span_us=3000)),
        ("8x8 periodic", Readout(2**20, RATE, Mode.COUNTER, 1, tuple(ReadoutSample(b, 19_600, 15_800) for b in grid64),
                                 span_us=3000)),
        ("8x8 event-based, at rest", Readout(2**20, RATE, Mode.COUNTER, 1, (), tuple(grid64), span_us=3000)),
    ]
    for name, r in records:
        payload = len(msgpack.packb(r.to_wire()))
        try:
            frames = [_readout_len(r)]
        except ProtocolError:  # more than one frame: the record in parts of at most 24 samples
            step = 24
            frames = [_readout_len(Readout(r.index, r.rate, r.mode, r.oversampling, r.samples[i:i + step],
                                           span_us=r.span_us, part=k, parts=-(-len(r.samples) // step)))
                      for k, i in enumerate(range(0, len(r.samples), step))]
        print(f"{name:<48} {payload:>10} {len(frames):>7} {sum(frames):>14} {sum(frames) / r.bridges():>10.1f}")


def main() -> None:
    pin_to_one_core()
    frame = Frame(7, 0, 7, 1, Data(Mode.COUNTER, (Sample(0, 40_000, 19_600, 15_800, 0),)), hops=3, cost=31)
    wire = encode(frame)
    frames = [Frame(7, 0, 7, i & 0xFFFF, frame.payload, 3, 31) for i in range(N)]
    wires = [encode(f) for f in frames]
    stream = b"".join(encode_stream(f) for f in frames)
    chunks = [stream[i:i + 4096] for i in range(0, len(stream), 4096)]  # typical serial read size

    def do_encode() -> None:
        for f in frames:
            encode(f)

    def do_decode() -> None:
        for w in wires:
            decode(w)

    def do_stream() -> None:
        d = StreamDecoder()
        got = 0
        for c in chunks:
            got += len(d.feed(c))
        assert got == N and not d.frames_dropped

    # Two gateways, the second 50 frames late: every frame arrives twice.
    twice = [f for i in range(50, N // 2 + 50) for f in (frames[i], frames[i - 50])]

    def do_host() -> None:
        rx = HostReceiver()
        got = sum(len(rx.receive(f, 1.0)) for f in twice)
        assert got == N // 2 + 50

    big = Frame(7, 0, 7, 0, Data(Mode.COUNTER, tuple(Sample(0, 40_000 + i, 19_600, 15_800, 0) for i in range(60))))
    parts: list[Frame] = []
    for d in range(N // 20):
        parts += fragment(Frame(7, 0, 7, len(parts) & 0xFFFF, big.payload), tag=d & 0xFFFF)
    parts_twice = [f for i in range(len(parts)) for f in (parts[i], parts[max(i - 50, 0)])]

    def do_host_fragments() -> None:
        rx = HostReceiver()
        got = sum(len(rx.receive(f, 1.0)) for f in parts_twice)
        assert got == N // 20

    five = Frame(7, 0, 7, 1, periodic_data(periodic(5, 9_000_000_123, 18_000)), hops=3, cost=31)
    fives = [encode(Frame(7, 0, 7, i & 0xFFFF, five.payload, 3, 31)) for i in range(N // 5)]

    def do_decode_five() -> None:
        for w in fives:
            decode(w)

    rows = [
        ("encode", best_rate(do_encode, N), None),
        ("decode", best_rate(do_decode, N), None),
        ("decode, 5-sample frames (per sample)", best_rate(do_decode_five, N), None),
        ("stream decode (COBS + decode, 4 KiB reads)", best_rate(do_stream, N), TARGET_STREAM),
        ("host receive, each frame twice (per copy)", best_rate(do_host, len(twice)), None),
        ("host receive, fragments twice (per copy)", best_rate(do_host_fragments, len(parts_twice)), None),
    ]
    print(f"DATA frame: {len(wire)} bytes ({len(encode_stream(frame)) - 1} on the serial line), {N} frames, best of 3")
    print(f"{'operation':<44} {'frames/s':>12} {'target':>10} {'ok':>4}")
    for name, rate, target in rows:
        ok = "" if target is None else ("yes" if rate >= target else "NO")
        print(f"{name:<44} {rate:>12,.0f} {'' if target is None else f'{target:,}':>10} {ok:>4}")
    bytes_per_sample()
    readout_bytes()


if __name__ == "__main__":
    main()
