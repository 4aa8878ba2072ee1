"""The subscriber examples in examples/ (Python, C, JavaScript), run against a live PUB socket.

All three take the same options (-e ENDPOINT -n COUNT [-s SERVER.key -k CLIENT.key_secret]
[TOPIC...]) and print {"topic", "payload"} JSON lines, so one test drives them all.
The C example is built with its Makefile where a compiler and the libzmq and
msgpack-c headers exist; the JavaScript one runs where node finds its npm packages
(``npm install`` in examples/javascript). Elsewhere they skip and say why.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from pathlib import Path

import pytest
import zmq
from cellbridge.daemon.ops.security import CurveKeys, CurveServer
from cellbridge.daemon.shell.keys import write_keypair

from support.example_subscribers import c_subscriber, js_subscriber, py_subscriber
from support.pub_helpers import json_lines, publisher, run_subscriber

EXAMPLE_COMMANDS: dict[str, Callable[[Path], list[str]]] = {
    "python": py_subscriber, "c": c_subscriber, "javascript": js_subscriber}


@pytest.mark.parametrize("language", EXAMPLE_COMMANDS)
def test_example_prints_the_topics_it_subscribed(language: str, tmp_path: Path) -> None:
    cmd = EXAMPLE_COMMANDS[language](tmp_path)
    with publisher() as endpoint:
        out = run_subscriber([*cmd, "-e", endpoint, "-n", "6", "contact", "raw"], cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    lines = json_lines(out.stdout)
    assert len(lines) == 6
    assert {ln["topic"] for ln in lines} <= {"contact", "raw"}  # health was not subscribed
    assert all(ln["payload"]["v"] == 1 and isinstance(ln["payload"]["t_host"], float) for ln in lines)
    contacts = [ln["payload"] for ln in lines if ln["topic"] == "contact"]
    raws = [ln["payload"] for ln in lines if ln["topic"] == "raw"]
    assert contacts and raws
    assert contacts[0]["contacts"] == [{"id": 3, "x": 12.5, "y": -3.25, "force": 0.75, "valid": True}]
    assert raws[0]["frame"] == "01fe" and raws[0]["bridge"] == 7  # bytes as hex, as `cellbridge sub` prints them


@pytest.mark.parametrize("language", EXAMPLE_COMMANDS)
def test_example_as_curve_client(language: str, tmp_path: Path) -> None:
    cmd = EXAMPLE_COMMANDS[language](tmp_path)
    (tmp_path / "clients").mkdir()
    server_pub, server_secret = write_keypair(tmp_path, "server")
    write_keypair(tmp_path / "clients", "arm")
    client_secret = tmp_path / "clients" / "arm.key_secret"
    context = zmq.Context()
    curve = CurveServer(context, CurveKeys(server_secret, tmp_path / "clients"))
    try:
        with publisher(setup=curve.apply, context=context) as endpoint:
            out = run_subscriber([*cmd, "-e", endpoint, "-n", "2", "-s", str(server_pub), "-k", str(client_secret),
                                  "health"], cwd=tmp_path)
    finally:
        curve.stop()
        context.term()
    assert out.returncode == 0, out.stderr
    assert [ln["topic"] for ln in json_lines(out.stdout)] == ["health", "health"]


@pytest.mark.parametrize("language", EXAMPLE_COMMANDS)
def test_example_reads_the_live_daemon(language: str, tmp_path: Path) -> None:
    """The same subscribers against a real `cellbridge daemon` fed a skin's traffic on a pty."""
    import threading

    from daemon_harness import Pty, daemon, write_config
    from daemon_traffic import GridFrames

    cmd = EXAMPLE_COMMANDS[language](tmp_path)
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "d.toml"
    ends = write_config(cfg, [{"name": "gw", "url": str(tmp_path / "gw")}])
    sk = GridFrames(rows=2, cols=2)
    stop = threading.Event()

    def feed() -> None:  # the gateway keeps talking while the subscriber reads
        k = 0
        while not stop.is_set():
            data = sk.slot(k)
            if k % 50 == 0:  # HELLOs again and again: the daemon may open the pty after the first ones
                data = sk.hellos() + sk.beacons() + data
            with contextlib.suppress(AssertionError):  # nobody reads (the daemon stopping): lost, as a device's
                pty.write(data, limit=30.0)
            k += 1
            stop.wait(0.01)

    feeder = threading.Thread(target=feed, daemon=True)
    try:
        with daemon(cfg):
            feeder.start()
            out = run_subscriber([*cmd, "-e", ends["pub"], "-n", "3", "element"], cwd=tmp_path, timeout=60)
    finally:
        stop.set()
        feeder.join(5)
        pty.close()
    assert out.returncode == 0, out.stderr
    lines = json_lines(out.stdout)
    assert len(lines) == 3 and {ln["topic"] for ln in lines} == {"element"}
    for ln in lines:
        p = ln["payload"]
        assert p["v"] == 2 and isinstance(p["t_host"], float)
        assert set(p["bridge"]) <= set(sk.ids) and len(p["c1"]) == len(p["bridge"])


@pytest.mark.parametrize("language", EXAMPLE_COMMANDS)
def test_example_prints_valid_json_where_a_value_is_not_a_number(language: str, tmp_path: Path) -> None:
    # an element's force is NaN where it is not valid; a σ along an axis the readings leave
    # open is infinite: JSON has neither, and every example prints null for both
    import json

    import msgpack

    cmd = EXAMPLE_COMMANDS[language](tmp_path)
    payload = {"v": 2, "seq": 0, "t_host": 1.7e9, "bridge": [1, 2], "force": [float("nan"), 1.5],
               "sigma": [float("inf"), float("-inf")]}
    with publisher(extra=[[b"element", msgpack.packb(payload)]]) as endpoint:
        out = run_subscriber([*cmd, "-e", endpoint, "-n", "2", "element"], cwd=tmp_path)
    assert out.returncode == 0, out.stderr

    def strict(token: str) -> None:
        raise AssertionError(f"not JSON: {token}")

    lines = [json.loads(line, parse_constant=strict) for line in out.stdout.splitlines() if line.strip()]
    assert lines and all(ln["payload"]["force"] == [None, 1.5] and ln["payload"]["sigma"] == [None, None]
                         for ln in lines)


@pytest.mark.parametrize("language", EXAMPLE_COMMANDS)
def test_example_prints_a_map_whose_keys_are_numbers_and_not_numbers(language: str, tmp_path: Path) -> None:
    # msgpack map keys may be any value: an int key prints as its digits, a NaN or infinite
    # float key as a string (a JSON key is one); the subscriber keeps running either way
    import json

    import msgpack

    cmd = EXAMPLE_COMMANDS[language](tmp_path)
    payload = {"v": 2, "t_host": 1.7e9, "bridges": {7: {"loss": float("nan")}, float("nan"): 1, float("inf"): 2}}
    with publisher(extra=[[b"health", msgpack.packb(payload, strict_types=False)]]) as endpoint:
        out = run_subscriber([*cmd, "-e", endpoint, "-n", "2", "health"], cwd=tmp_path)
    assert out.returncode == 0, out.stderr

    def strict(token: str) -> None:
        raise AssertionError(f"not JSON: {token}")

    lines = [json.loads(line, parse_constant=strict) for line in out.stdout.splitlines() if line.strip()]
    odd = [ln["payload"]["bridges"] for ln in lines if "bridges" in ln["payload"]]
    assert odd and all(len(b) == 3 and b["7"] == {"loss": None} and {v for k, v in b.items() if k != "7"} == {1, 2}
                       for b in odd), odd
