"""What a hostile local client can make the daemon hold: descriptors and memory.

Run: ``.venv/bin/python bench/bench_limits.py [--connections N] [--request-mb M]``.

The daemon runs as a real process with the descriptor limit systemd gives a service by
default (soft = hard = 1024 here, so it cannot raise it), one pty gateway link, and the
default ``[peers]`` and ``[control]`` settings. Then:

1. **Idle connections.** N plain TCP connects to the control port and N/2 to the PUB
   port, none of which ever speaks ZMTP. Printed: the descriptors the daemon holds while
   they stay open, whether a control ping is still answered, and whether the gateway
   line comes back after a blip (the pty closed and reopened).
2. **A huge control request.** One request of M MB (a ping whose ``id`` is M MB of
   text). Printed: the daemon's resident memory before, its peak (``VmHWM``), 5 s
   later, the size of the reply, and whether a normal ping is answered afterwards;
   then the reply to a 200 kB one.

Figures are the daemon's own (``/proc/PID``); nothing here is timed against a target.
"""

from __future__ import annotations

import argparse
import resource
import socket
import sys
import tempfile
import time
from pathlib import Path

import msgpack
import zmq

from daemon_harness import Client, Pty, daemon, idle_connects, open_descriptors, proc_status_kb, write_config


def _limit_fds() -> None:
    resource.setrlimit(resource.RLIMIT_NOFILE, (1024, 1024))


def ping(client: Client, timeout: float = 5.0) -> bool:
    try:
        return bool(client.request({"v": 1, "cmd": "ping"}, timeout)["ok"])
    except AssertionError:
        return False


def link_up_after_blip(pty: Pty, client: Client, timeout: float = 10.0) -> bool:
    pty.close()
    time.sleep(0.5)
    pty.open()
    try:
        client.wait_for("health", lambda m: m["links"]["gw"]["connected"] and m["links"]["gw"]["reconnects"] >= 1,
                        timeout=timeout)
        return True
    except (AssertionError, KeyError):
        return False


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--connections", type=int, default=2000)
    ap.add_argument("--request-mb", type=int, default=500)
    args = ap.parse_args()
    resource.setrlimit(resource.RLIMIT_NOFILE, (resource.getrlimit(resource.RLIMIT_NOFILE)[1],) * 2)
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        pty = Pty(tmp_path / "gw")
        cfg = tmp_path / "daemon.toml"
        endpoints = write_config(cfg, [{"name": "gw", "url": pty.link, "reconnect_min": 0.05, "reconnect_max": 0.5}],
                                 contact={"enabled": False})
        client = Client(endpoints, (b"health",))
        held: list[socket.socket] = []
        try:
            with daemon(cfg, tmp_path / "stderr.log", preexec_fn=_limit_fds) as proc:
                client.ready()
                print(f"daemon pid {proc.pid}, RLIMIT_NOFILE 1024:1024, {open_descriptors(proc.pid)} descriptors at rest")
                held = idle_connects(endpoints["control"], args.connections)
                held += idle_connects(endpoints["pub"], args.connections // 2)
                time.sleep(3.0)
                print(f"{len(held)} idle connections open ({args.connections} control, {args.connections // 2} pub)")
                print(f"  descriptors held by the daemon: {open_descriptors(proc.pid)}")
                print(f"  control ping answered: {ping(client)}")
                print(f"  gateway line back after a blip: {link_up_after_blip(pty, client)}")
                print(f"  descriptors held by the daemon: {open_descriptors(proc.pid)}")
                for s in held:
                    s.close()
                held = []
                time.sleep(1.0)
                if not ping(client, 10.0):
                    print("  control does not answer after the connections closed; stopping")
                    return 1
                before = proc_status_kb(proc.pid, "VmRSS")
                size = args.request_mb * 1_000_000
                body = msgpack.packb({"v": 1, "cmd": "ping", "id": "x" * size})
                req = client.ctx.socket(zmq.REQ)
                req.setsockopt(zmq.LINGER, 0)
                req.connect(endpoints["control"])
                t0 = time.monotonic()
                req.send(body)
                del body
                reply_size = -1
                if req.poll(30_000):
                    reply_size = len(req.recv())
                req.close()
                elapsed = time.monotonic() - t0
                time.sleep(5.0)
                print(f"one {args.request_mb} MB control request:")
                print(f"  resident memory before {before / 1024:.0f} MB, peak {proc_status_kb(proc.pid, 'VmHWM') / 1024:.0f} MB, "
                      f"5 s later {proc_status_kb(proc.pid, 'VmRSS') / 1024:.0f} MB")
                print(f"  reply: {reply_size} bytes after {elapsed:.1f} s (-1: none, the connection was dropped)")
                print(f"  control ping answered afterwards: {ping(client)}")
                small = client.request({"v": 1, "cmd": "ping", "id": "x" * 200_000}, 10.0)
                print(f"a 200 kB request: ok={small['ok']}, reply {len(msgpack.packb(small))} bytes, "
                      f"error {small.get('error', '')!r}")
        finally:
            for s in held:
                s.close()
            client.close()
            pty.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
