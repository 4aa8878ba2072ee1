"""Health's per-bridge ``loss`` on a real-time skin: real bridge processes (``mesh up``),
their gateway pty read with pyserial and fed to the daemon's pipeline at host monotonic
time, as the daemon does. Prints, per bridge, the frames and samples health counted, the
frames it finds lost, its ``loss``, and the samples the bridge says it sent (its counters
at exit): with every frame for the host numbered in one sequence (docs/protocol.md §1),
``loss`` is the share of frames that did not arrive, not the link acks and beacons the
host never sees (the gateway bridge showed ~0.93 while delivering every sample).

    .venv/bin/python bench/bench_health_loss.py [--grid 4] [--seconds 20] [--rate 100]
"""

from __future__ import annotations

import argparse
import time

import serial
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.emulator.mesh import meshgen

from realskin import RealSkin, read_now


class PipelineSkin(RealSkin):
    """A real skin whose gateway bytes go into one daemon pipeline (one link per gateway)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        links = [{"name": f"gw{i}", "url": "/dev/null"} for i in range(len(self.mesh.gateways))]
        self.pipeline = Pipeline(parse_config({"link": links}))
        self._devices: list[str] = []

    def _read(self, device: str) -> None:
        with self._lock:
            self._devices.append(device)
            link = f"gw{len(self._devices) - 1}"  # one link per gateway pty, in the order mesh up names them
        port = serial.Serial(device, timeout=0.05)
        try:
            while not self._stop.is_set():
                chunk = read_now(port)
                if chunk:
                    now = time.monotonic()
                    with self._lock:
                        self.pipeline.feed(link, chunk, now)
        finally:
            port.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--grid", type=int, default=4, help="an N x N skin, gateway 1 (default 4)")
    ap.add_argument("--seconds", type=float, default=20.0, help="how long to read (default 20)")
    ap.add_argument("--rate", type=int, default=100, help="samples per second per bridge (default 100)")
    args = ap.parse_args()
    mesh = meshgen.grid(args.grid, args.grid)
    with PipelineSkin(mesh, rate=args.rate) as skin:
        time.sleep(args.seconds)
        with skin._lock:
            health = skin.pipeline.health_body(time.monotonic())["bridges"]
    print(f"{args.grid}x{args.grid} skin, {args.rate} Hz, periodic, {args.seconds:.0f} s, real processes")
    print(f"{'bridge':>6} {'frames':>7} {'lost':>5} {'loss':>7} {'samples':>8} {'sent':>7} {'delivered':>9}")
    worst = 0.0
    for b in sorted(mesh.ids):
        h = health.get(str(b))
        sent = skin.counters.get(b, {}).get("samples_sent", 0)
        if h is None:
            print(f"{b:>6} {'-':>7} {'-':>5} {'-':>7} {0:>8} {sent:>7} {'-':>9}")
            continue
        worst = max(worst, h["loss"])
        share = h["samples"] / sent if sent else float("nan")
        print(f"{b:>6} {h['frames']:>7} {h['lost']:>5} {h['loss']:>7.4f} {h['samples']:>8} {sent:>7} {share:>9.4f}")
    print(f"worst loss {worst:.4f}")
    print("(sent: the bridge's count at exit, after the reader stopped: the last ~0.1 s of samples were never read)")


if __name__ == "__main__":
    main()
