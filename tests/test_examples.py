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
from support.process_state import first_stderr_line
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


# The examples' ends: each a sentence and an exit status, never a traceback (Ctrl-C: exit 0).


@pytest.mark.parametrize("language", EXAMPLE_COMMANDS)
def test_example_says_when_nothing_comes_and_ends_quietly_on_ctrl_c(language: str, tmp_path: Path) -> None:
    # No daemon on the endpoint: the subscriber waited without a word, and Ctrl-C then
    # ended it in a KeyboardInterrupt traceback (Python), with exit 1 (C), or 130 (JavaScript).
    import os
    import signal
    import subprocess

    from daemon_harness import free_port

    endpoint = f"tcp://127.0.0.1:{free_port()}"  # nobody publishes there
    proc = subprocess.Popen([*EXAMPLE_COMMANDS[language](tmp_path), "-e", endpoint], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True)
    try:
        said = first_stderr_line(proc)
        assert b"is the daemon running" in said and endpoint.encode() in said, said
        assert proc.poll() is None  # it waits on: a daemon started later is read
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C, as the terminal sends it
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert proc.returncode == 0, err
    assert b"Traceback" not in said + err and out == b"", err


@pytest.mark.parametrize(("args", "says"), [
    (["-e", "robot:5560"], "robot:5560"),  # no transport: ZeroMQ refuses it
    (["-s", "missing.key", "-k", "missing.key_secret"], "missing.key"),
    (["-s", "server.key"], "-k"),  # CURVE needs both keys: one alone was ignored, and nothing came
    (["-n", "-1"], "-n"),  # printed nothing and exited 0
    (["-n", "ten"], "-n"),
])
def test_python_example_refuses_bad_arguments_in_a_sentence(tmp_path: Path, args: list[str], says: str) -> None:
    (tmp_path / "server.key").write_text("not a certificate\n")
    out = run_subscriber([*py_subscriber(tmp_path), *args], cwd=tmp_path, timeout=30)
    assert out.returncode == 2, (out.stdout, out.stderr)
    assert says in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_python_example_ends_quietly_when_its_reader_goes_away(tmp_path: Path) -> None:
    # subscriber.py | head -1: the pipe closes under it, the end of the output, not an error
    with publisher() as endpoint:
        out = run_subscriber(["sh", "-c", f'"$0" "$1" -e {endpoint} | head -n 1', *py_subscriber(tmp_path)],
                             cwd=tmp_path, timeout=30)
    assert out.returncode == 0, out.stderr
    assert len(json_lines(out.stdout)) == 1 and out.stderr == "", out.stderr


def test_python_example_reads_on_past_a_message_it_cannot_decode(tmp_path: Path) -> None:
    # a payload that is not msgpack, or a message of three frames, ended it in a traceback;
    # now each is a line with "error" (as the C example and `cellbridge sub` print it)
    with publisher(extra=[[b"contact", b"\xc1"], [b"health", b"a", b"b"]]) as endpoint:
        out = run_subscriber([*py_subscriber(tmp_path), "-e", endpoint, "-n", "12"], cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    lines = json_lines(out.stdout)
    assert len(lines) == 12 and "Traceback" not in out.stderr
    errors = {ln["topic"]: ln["error"] for ln in lines if "error" in ln}
    assert errors == {"contact": "payload is not msgpack", "health": "expected 2 frames [topic, payload]"}, lines


@pytest.mark.parametrize("language", EXAMPLE_COMMANDS)
def test_example_of_a_quiet_topic_of_a_running_daemon_does_not_ask_whether_it_runs(language: str,
                                                                                   tmp_path: Path) -> None:
    # an idle skin publishes no contact: the daemon's health, every second, says it runs
    import os
    import signal
    import subprocess
    import time

    with publisher() as endpoint:  # contact, health and raw; never topology
        proc = subprocess.Popen([*EXAMPLE_COMMANDS[language](tmp_path), "-e", endpoint, "topology"],
                                stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, start_new_session=True)
        try:
            time.sleep(7)
            os.killpg(proc.pid, signal.SIGINT)
            _, err = proc.communicate(timeout=10)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0 and err == b"", err


def readme_subscriber() -> str:
    """The README's inline Python subscriber, as written there."""
    import re

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    blocks = [b for b in re.findall(r"```python\n(.*?)```", readme, re.S) if "recv_multipart" in b]
    assert len(blocks) == 1, "the README's Python subscriber snippet"
    return blocks[0]


def test_readme_subscriber_prints_contacts_and_ends_quietly_on_ctrl_c(tmp_path: Path) -> None:
    # the README's snippet, run as written, ended in a KeyboardInterrupt traceback on Ctrl-C
    import os
    import signal
    import subprocess
    import sys
    import time

    import msgpack

    code = readme_subscriber()
    assert "tcp://127.0.0.1:5560" in code  # the daemon's default endpoint: published on here when free
    context = zmq.Context()
    pub: zmq.Socket[bytes] | None = context.socket(zmq.PUB)
    assert pub is not None
    pub.linger = 0
    try:
        pub.bind("tcp://127.0.0.1:5560")
    except zmq.ZMQError:  # a daemon of another run holds the default port: Ctrl-C is tested alone
        pub.close()
        pub = None
    # (-u: its stdout is a pipe here, not a terminal)
    proc = subprocess.Popen([sys.executable, "-u", "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            cwd=tmp_path, start_new_session=True)
    try:
        assert proc.stdout is not None
        if pub is not None:
            os.set_blocking(proc.stdout.fileno(), False)
            printed = b""
            contact = msgpack.packb({"v": 1, "seq": 0, "t_host": 1.7e9,
                                     "contacts": [{"id": 1, "x": 0.057, "y": 0.04, "force": 3.0}]})
            end = time.monotonic() + 30
            while b"\n" not in printed and time.monotonic() < end and proc.poll() is None:
                pub.send_multipart([b"contact", contact])
                time.sleep(0.1)
                printed += proc.stdout.read() or b""
            assert printed.split(b"\n")[0] == b"0.057 0.04 3.0", printed
        else:
            time.sleep(2)
        assert proc.poll() is None
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C, as the terminal sends it
        _, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        if pub is not None:
            pub.close()
        context.term()
    assert proc.returncode == 0 and err == b"", err
