"""Loopback by default, CURVE for anything else: check_bind, load_curve and CurveServer on real sockets.

Non-loopback endpoints are only judged here, never bound.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import pytest
import zmq
from cellbridge.daemon.ops.security import (
    CurveKeys,
    CurveServer,
    SecurityError,
    apply_client,
    check_bind,
    is_loopback,
    load_curve,
)
from cellbridge.daemon.shell.keys import write_keypair
from hypothesis import given
from hypothesis import strategies as st

LOOPBACK = ["tcp://127.0.0.1:5561", "tcp://127.0.0.53:5560", "tcp://localhost:5561", "tcp://[::1]:5561",
            "tcp://lo:5561", "tcp://[::ffff:127.0.0.1]:5561", "ipc:///run/cellbridge/control", "inproc://control",
            "tcp://127.0.0.1:*"]
EXPOSED = ["tcp://0.0.0.0:5561", "tcp://*:5561", "tcp://192.0.2.1:5561", "tcp://[::]:5561", "tcp://eth0:5561",
           "tcp://robot.example:5561", "tcp://[2001:db8::1]:5561", "udp://127.0.0.1:5561", "pgm://eth0;239.0.0.1:5555",
           "127.0.0.1:5561", "tcp://10.0.0.127:5561"]


@pytest.fixture
def keys(tmp_path: Path) -> dict[str, Path]:
    (tmp_path / "clients").mkdir()
    (tmp_path / "other").mkdir()
    server_pub, server_secret = write_keypair(tmp_path, "server")
    write_keypair(tmp_path / "clients", "arm")
    write_keypair(tmp_path / "other", "stranger")
    return {"server.key": server_pub, "server.key_secret": server_secret, "clients": tmp_path / "clients",
            "arm": tmp_path / "clients" / "arm.key_secret", "stranger": tmp_path / "other" / "stranger.key_secret"}


@pytest.mark.parametrize("endpoint", LOOPBACK)
def test_loopback_binds_are_accepted_without_keys(endpoint: str) -> None:
    assert is_loopback(endpoint)
    check_bind(endpoint, None)


@pytest.mark.parametrize("endpoint", EXPOSED)
def test_exposed_binds_are_refused_without_keys(endpoint: str) -> None:
    assert not is_loopback(endpoint)
    with pytest.raises(SecurityError, match="refusing to bind .*cellbridge keys gen"):
        check_bind(endpoint, None)


@pytest.mark.parametrize("endpoint", EXPOSED)
def test_exposed_binds_are_accepted_with_keys(endpoint: str, keys: dict[str, Path]) -> None:
    check_bind(endpoint, CurveKeys(keys["server.key_secret"], keys["clients"]))


@given(st.ip_addresses(), st.integers(1, 65535))
def test_loopback_is_exactly_the_loopback_addresses(address, port: int) -> None:
    host = f"[{address}]" if address.version == 6 else str(address)
    assert is_loopback(f"tcp://{host}:{port}") == (address.is_loopback or (
        address.version == 6 and address.ipv4_mapped is not None and address.ipv4_mapped.is_loopback))


def test_load_curve_reads_the_security_table(keys: dict[str, Path], tmp_path: Path) -> None:
    assert load_curve(None) is None and load_curve({}) is None
    curve = load_curve({"server_secret_file": "server.key_secret", "allowed_clients_dir": "clients"},
                       base_dir=tmp_path)
    assert curve == CurveKeys(tmp_path / "server.key_secret", tmp_path / "clients")


def test_load_curve_expands_environment_variables(keys: dict[str, Path], tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CREDENTIALS_DIRECTORY", str(tmp_path))
    curve = load_curve({"server_secret_file": "${CREDENTIALS_DIRECTORY}/server.key_secret",
                        "allowed_clients_dir": str(keys["clients"])})
    assert curve is not None and curve.server_secret_file == tmp_path / "server.key_secret"


@pytest.mark.parametrize(("section", "message"), [
    ({"server_secret_file": "server.key_secret"}, "allowed_clients_dir is missing"),
    ({"server_secret_file": "server.key_secret", "allowed_clients_dir": "clients", "allow": "all"},
     "unknown key 'allow'"),
    ({"server_secret_file": 5, "allowed_clients_dir": "clients"}, "server_secret_file must be a non-empty path"),
    ({"server_secret_file": "nope.key_secret", "allowed_clients_dir": "clients"}, "server_secret_file .*nope"),
    ({"server_secret_file": "server.key", "allowed_clients_dir": "clients"},
     "server_secret_file .* holds only a public key"),
    ({"server_secret_file": "server.key_secret", "allowed_clients_dir": "server.key"},
     "allowed_clients_dir .* is not a directory"),
    ({"server_secret_file": "loose.key_secret", "allowed_clients_dir": "clients"},
     r"server_secret_file .* readable by group or others \(mode 0640\)"),
    ({"server_secret_file": "server.key_secret", "allowed_clients_dir": "empty"},
     "allowed_clients_dir .* holds no public key file"),
])
def test_load_curve_names_the_bad_key(section: dict[str, object], message: str, keys: dict[str, Path],
                                      tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    loose = tmp_path / "loose.key_secret"
    loose.write_bytes(keys["server.key_secret"].read_bytes())
    loose.chmod(0o640)
    with pytest.raises(ValueError, match=rf"daemon.toml: \[security\]: {message}"):
        load_curve(section, source="daemon.toml", base_dir=tmp_path)


@contextlib.contextmanager
def curve_server(keys: dict[str, Path], kind: int) -> Iterator[tuple[zmq.Context, zmq.Socket, str, CurveServer]]:
    """A REP or ROUTER socket made a CURVE server through CurveServer, bound on 127.0.0.1."""
    context = zmq.Context()
    curve = CurveServer(context, CurveKeys(keys["server.key_secret"], keys["clients"]))
    server = context.socket(kind)
    server.linger = 0
    try:
        curve.apply(server)
        server.bind("tcp://127.0.0.1:*")
        yield context, server, server.get_string(zmq.LAST_ENDPOINT), curve
    finally:
        server.close()
        curve.stop()
        context.term()


def ask(context: zmq.Context, server: zmq.Socket, endpoint: str, server_key: Path | None,
        client_key: Path | None) -> bytes | None:
    """Send b"ping" as a client and serve it; None when the server hears nothing within a second."""
    router = server.type == zmq.ROUTER
    client = context.socket(zmq.DEALER if router else zmq.REQ)
    client.linger = 0
    try:
        if server_key is not None and client_key is not None:
            apply_client(client, server_key, client_key)
        client.connect(endpoint)
        client.sndtimeo = 1000  # a REQ with no peer (its handshake failed, the pipe torn down) blocks in send
        try:
            client.send(b"ping")
        except zmq.Again:
            return None
        if not server.poll(1000):  # the handshake failed: the request never reached the server
            return None
        *identity, body = server.recv_multipart()
        server.send_multipart([*identity, body + b"-pong"])
        return client.recv() if client.poll(1000) else None
    finally:
        client.close()


@pytest.mark.parametrize("kind", [zmq.REP, zmq.ROUTER], ids=["REP", "ROUTER"])
def test_allowed_key_gets_replies_foreign_key_and_plain_clients_get_none(kind: int, keys: dict[str, Path]) -> None:
    with curve_server(keys, kind) as (context, server, endpoint, curve):
        assert ask(context, server, endpoint, keys["server.key"], keys["arm"]) == b"ping-pong"
        assert ask(context, server, endpoint, keys["server.key"], keys["stranger"]) is None
        assert ask(context, server, endpoint, None, None) is None  # no CURVE at all
        assert ask(context, server, endpoint, keys["server.key"], keys["arm"]) == b"ping-pong"  # still serving
        counters = curve.counters()
    assert counters["allowed_keys"] == 1
    assert counters["handshakes_accepted"] == 2 and counters["handshakes_denied"] >= 1  # a refused client retries


def test_reload_admits_a_newly_allowed_key(keys: dict[str, Path]) -> None:
    with curve_server(keys, zmq.ROUTER) as (context, server, endpoint, curve):
        stranger_public = keys["stranger"].with_suffix(".key")
        assert ask(context, server, endpoint, keys["server.key"], keys["stranger"]) is None
        (keys["clients"] / "stranger.key").write_bytes(stranger_public.read_bytes())
        assert ask(context, server, endpoint, keys["server.key"], keys["stranger"]) is None  # not before the reload
        curve.reload()
        assert ask(context, server, endpoint, keys["server.key"], keys["stranger"]) == b"ping-pong"
        (keys["clients"] / "broken.key").write_text("no key here\n")
        with pytest.raises(ValueError, match="allowed_clients_dir .*broken.key"):
            curve.reload()
        assert curve.counters()["allowed_keys"] == 2  # the previous keys stay in force


def test_apply_client_names_a_bad_key_file(keys: dict[str, Path], tmp_path: Path) -> None:
    context = zmq.Context()
    sock = context.socket(zmq.SUB)
    try:
        with pytest.raises(ValueError, match="arm.key: holds no secret key"):
            apply_client(sock, keys["server.key"], keys["clients"] / "arm.key")
        with pytest.raises(ValueError, match="missing.key: cannot read"):
            apply_client(sock, tmp_path / "missing.key", keys["arm"])
    finally:
        sock.close(linger=0)
        context.term()


def test_stop_returns_when_the_zap_thread_has_died(keys: dict[str, Path]) -> None:
    """pyzmq's stop sends TERMINATE on a pipe nobody reads once the ZAP thread died, and
    blocks there: the daemon hung at its stop until the service manager killed it. The
    stop is bounded and says the thread is gone."""
    import threading

    context = zmq.Context()
    curve = CurveServer(context, CurveKeys(keys["server.key_secret"], keys["clients"]))
    try:
        zap = curve._auth.thread
        curve._auth.pipe.send(b"TERMINATE")  # the ZAP thread ends behind the server's back ...
        zap.join(5)
        assert not zap.is_alive()  # ... and its end of the pipe is closed
        result: list[bool] = []
        stopper = threading.Thread(target=lambda: result.append(curve.stop()), daemon=True)
        stopper.start()
        stopper.join(10)
        assert not stopper.is_alive(), "CurveServer.stop() blocked"
        assert result == [True]
    finally:
        if curve._auth.pipe is None:  # (a blocked stop leaves its pipe open: the context would never end)
            context.term()
