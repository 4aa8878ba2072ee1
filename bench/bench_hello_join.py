"""Time one bridge's HELLO joining a skin already placed by HELLO: what blocks the loop.

Run: ``.venv/bin/python bench/bench_hello_join.py [--bridges N]``.

Places N bridges (a 32-wide grid of 20 mm elements) from their HELLOs through
``Pipeline.feed``, then times the feed of one more bridge's HELLO (a join, checked
alone against the placed elements), the feed of a HELLO moving a placed bridge, and
``layout_from_geometry`` (a full placement) on the whole skin alone, and prints them.
"""

from __future__ import annotations

import argparse
import time

from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.layout import layout_from_geometry
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.protocol import Frame, Hello, encode_stream


def _hello(bid: int, x: float, y: float, seq: int = 0) -> bytes:
    return encode_stream(Frame(src=1, dst=0, origin=bid, seq=seq, payload=Hello(bid, "bench", x, y, 0.02, 50_000_000, 3)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bridges", type=int, default=1000)
    n = ap.parse_args().bridges
    geometry = {i + 1: ((i % 32) * 0.02, (i // 32) * 0.02, 0.02) for i in range(n + 1)}
    p = Pipeline(parse_config({"link": [{"name": "gw", "url": "/dev/null"}]}))
    p.feed("gw", b"".join(_hello(b, x, y) for b, (x, y, _) in geometry.items() if b <= n), 0.0)
    x, y, _ = geometry[n + 1]
    t0 = time.perf_counter()
    p.feed("gw", _hello(n + 1, x, y), 1.0)
    join = time.perf_counter() - t0
    t0 = time.perf_counter()
    p.feed("gw", _hello(1, -1.0, -1.0, seq=1), 2.0)  # bridge 1 moves off the grid
    move = time.perf_counter() - t0
    t0 = time.perf_counter()
    layout_from_geometry(geometry)
    alone = time.perf_counter() - t0
    print(f"{'bridges':>8} {'join: feed ms':>14} {'move: feed ms':>14} {'full placement ms':>18} {'elements':>9}")
    print(f"{n:>8} {join * 1e3:>14.1f} {move * 1e3:>14.1f} {alone * 1e3:>18.1f} "
          f"{p.skin.layout.n if p.skin.layout else 0:>9}")


if __name__ == "__main__":
    main()
