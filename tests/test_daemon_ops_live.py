"""The daemon process itself: systemd notification, loopback-only binds, CURVE clients."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import time
from pathlib import Path

import msgpack
import zmq
import zmq.auth

from daemon_harness import CLI, Pty, daemon, free_port, write_config


def _notifications(sock: socket.socket, until: str, timeout: float) -> list[str]:
    got: list[str] = []
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        sock.settimeout(max(0.01, end - time.monotonic()))
        try:
            got += sock.recv(4096).decode().splitlines()
        except TimeoutError:
            break
        if until in got:
            break
    return got


def test_the_daemon_speaks_sd_notify_ready_watchdog_and_stopping(tmp_path: Path) -> None:
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "d.toml"
    write_config(cfg, [{"name": "gw", "url": str(tmp_path / "gw")}])
    name = f"cellbridge-test-{os.getpid()}-{time.monotonic_ns()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)  # the manager's end, in the abstract namespace
    env = dict(os.environ, NOTIFY_SOCKET="@" + name, WATCHDOG_USEC="200000")
    env.pop("WATCHDOG_PID", None)
    try:
        with daemon(cfg, env=env) as proc:
            first = _notifications(sock, "READY=1", 60)
            assert "READY=1" in first
            assert any(line.startswith("STATUS=") for line in first)
            later = _notifications(sock, "WATCHDOG=1", 5)
            assert "WATCHDOG=1" in first + later  # every 0.1 s: half of WATCHDOG_USEC
            os.killpg(proc.pid, signal.SIGTERM)
            assert "STOPPING=1" in _notifications(sock, "STOPPING=1", 15)
            assert proc.wait(15) == 0
    finally:
        sock.close()
        pty.close()


def test_a_bind_beyond_loopback_without_keys_is_refused_before_start(tmp_path: Path) -> None:
    cfg = tmp_path / "d.toml"
    write_config(cfg, [{"name": "gw", "url": str(tmp_path / "gw")}],
                 control={"endpoint": f"tcp://0.0.0.0:{free_port()}"})
    for extra in (["--check"], []):
        r = subprocess.run([CLI, "daemon", "--config", str(cfg), *extra], capture_output=True, text=True, timeout=60)
        assert r.returncode == 2
        assert "refusing to bind" in r.stderr and "0.0.0.0" in r.stderr and "[security]" in r.stderr


def _key_pair(path: Path) -> tuple[bytes, bytes]:
    """A client's (public, secret) keys, from its secret key file (which holds both)."""
    public, secret = zmq.auth.load_certificate(str(path))
    assert secret is not None, path
    return public, secret


def _status(ctx: zmq.Context, endpoint: str, server_public: bytes, client_pair: tuple[bytes, bytes] | None,
            timeout: float) -> dict | None:
    req = ctx.socket(zmq.REQ)
    req.setsockopt(zmq.LINGER, 0)
    if client_pair is not None:
        req.curve_serverkey = server_public
        req.curve_publickey, req.curve_secretkey = client_pair
    req.connect(endpoint)
    try:
        req.send(msgpack.packb({"v": 1, "cmd": "ping"}))
        return msgpack.unpackb(req.recv()) if req.poll(int(timeout * 1000)) else None
    finally:
        req.close()


def test_with_curve_an_allowed_client_gets_replies_and_a_foreign_one_nothing(tmp_path: Path) -> None:
    keys, allowed = tmp_path / "keys", tmp_path / "allowed"
    allowed.mkdir()
    keys.mkdir()
    for name, where in (("server", keys), ("robot", keys), ("stranger", keys)):
        subprocess.run([CLI, "keys", "gen", name, "--dir", str(where)], check=True, capture_output=True, timeout=60)
    (allowed / "robot.key").write_bytes((keys / "robot.key").read_bytes())
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "d.toml"
    ends = write_config(cfg, [{"name": "gw", "url": str(tmp_path / "gw")}])
    with open(cfg, "a") as f:
        f.write(f'[security]\nserver_secret_file = "{keys / "server.key_secret"}"\nallowed_clients_dir = "{allowed}"\n')
    server_public, _ = zmq.auth.load_certificate(str(keys / "server.key"))
    robot, stranger = (_key_pair(keys / f"{who}.key_secret") for who in ("robot", "stranger"))
    ctx = zmq.Context()
    try:
        with daemon(cfg):
            reply = None
            end = time.monotonic() + 60
            while reply is None and time.monotonic() < end:
                reply = _status(ctx, ends["control"], server_public, robot, 2.0)
            assert reply is not None and reply.get("ok") is True
            assert _status(ctx, ends["control"], server_public, stranger, 1.5) is None
            assert _status(ctx, ends["control"], server_public, None, 1.5) is None  # plain client
    finally:
        ctx.destroy(linger=0)
        pty.close()
