"""Protocol throughput on one core: encode, decode and serial stream decoding.

Run: ``.venv/bin/python bench/bench_protocol.py`` (or ``make bench``). The frame is
a DATA frame with one sample, 32 bytes on the wire before COBS: the smallest frame
a bridge sends, so the per-frame cost dominates. Target: >= 200 000 decoded
frames/s through the stream decoder.
"""

from __future__ import annotations

from timing import best_rate, pin_to_one_core

from cellbridge.protocol import (
    Data,
    Frame,
    HostReceiver,
    Mode,
    Sample,
    StreamDecoder,
    decode,
    encode,
    encode_stream,
    fragment,
)

N = 200_000
TARGET_STREAM = 200_000


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
    parts = []
    for d in range(N // 20):
        parts += fragment(Frame(7, 0, 7, len(parts) & 0xFFFF, big.payload), tag=d & 0xFFFF)
    parts_twice = [f for i in range(len(parts)) for f in (parts[i], parts[max(i - 50, 0)])]

    def do_host_fragments() -> None:
        rx = HostReceiver()
        got = sum(len(rx.receive(f, 1.0)) for f in parts_twice)
        assert got == N // 20

    rows = [
        ("encode", best_rate(do_encode, N), None),
        ("decode", best_rate(do_decode, N), None),
        ("stream decode (COBS + decode, 4 KiB reads)", best_rate(do_stream, N), TARGET_STREAM),
        ("host receive, each frame twice (per copy)", best_rate(do_host, len(twice)), None),
        ("host receive, fragments twice (per copy)", best_rate(do_host_fragments, len(parts_twice)), None),
    ]
    print(f"DATA frame: {len(wire)} bytes ({len(encode_stream(frame)) - 1} on the serial line), {N} frames, best of 3")
    print(f"{'operation':<44} {'frames/s':>12} {'target':>10} {'ok':>4}")
    for name, rate, target in rows:
        ok = "" if target is None else ("yes" if rate >= target else "NO")
        print(f"{name:<44} {rate:>12,.0f} {'' if target is None else f'{target:,}':>10} {ok:>4}")


if __name__ == "__main__":
    main()
