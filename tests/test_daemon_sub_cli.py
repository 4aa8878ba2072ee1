"""`cellbridge sub` (the installed command) against a live PUB socket publishing daemon-shaped messages."""

from __future__ import annotations

import json
import math
from pathlib import Path

import msgpack
import pytest
import zmq
from cellbridge.daemon.ops.security import CurveKeys, CurveServer
from cellbridge.daemon.shell.keys import write_keypair
from cellbridge.daemon.shell.subscribe import message_to_json
from hypothesis import given
from hypothesis import strategies as st

from daemon_harness import CLI
from support.process_state import first_stderr_line
from support.pub_helpers import json_lines, publisher, run_subscriber


def test_sub_prints_subscribed_topics_as_json_lines() -> None:
    with publisher() as endpoint:
        out = run_subscriber([CLI, "sub", "contact", "health", "--endpoint", endpoint, "--count", "6",
                              "--timeout", "20"])
    assert out.returncode == 0, out.stderr
    lines = json_lines(out.stdout)
    assert len(lines) == 6 and {ln["topic"] for ln in lines} == {"contact", "health"}
    assert all(ln["payload"]["v"] == 1 and isinstance(ln["payload"]["t_host"], float) for ln in lines)
    assert json.loads(out.stderr.splitlines()[-1]) == {"received": 6, "malformed": 0}


def test_sub_shows_malformed_messages_and_counts_them() -> None:
    extra = [[b"raw", b"\xc1"], [b"topology", b"\x80", b"third frame"]]
    with publisher(extra=extra) as endpoint:
        out = run_subscriber([CLI, "sub", "raw", "topology", "--endpoint", endpoint, "--count", "12",
                              "--timeout", "20"])
    assert out.returncode == 0, out.stderr
    lines = json_lines(out.stdout)
    bad = [ln for ln in lines if "error" in ln]
    assert any(ln["topic"] == "raw" and "not msgpack" in ln["error"] and ln["raw"] == "c1" for ln in bad)
    assert any(ln["topic"] == "topology" and "expected 2 frames" in ln["error"] for ln in bad)
    good = [ln for ln in lines if "payload" in ln]
    assert all(ln["payload"]["frame"] == "01fe" for ln in good)  # bytes as hex
    assert json.loads(out.stderr.splitlines()[-1]) == {"received": 12, "malformed": len(bad)}


def test_sub_times_out_with_status_1() -> None:
    with publisher() as endpoint:
        out = run_subscriber([CLI, "sub", "serial", "--endpoint", endpoint, "--timeout", "0.3"])  # never published here
    assert out.returncode == 1 and "no message for 0.3 s" in out.stderr


def test_sub_says_when_nothing_comes_and_waits_on() -> None:
    # `cellbridge sub` with no daemon on the endpoint waited without a word, for ever
    import os
    import signal
    import subprocess

    from daemon_harness import free_port

    endpoint = f"tcp://127.0.0.1:{free_port()}"  # nobody publishes there
    proc = subprocess.Popen([CLI, "sub", "--endpoint", endpoint], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        said = first_stderr_line(proc)
        assert b"is the daemon running" in said and endpoint.encode() in said, said
        assert proc.poll() is None  # waiting on: a daemon started later is read
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert proc.returncode == 0 and out == b"" and b"Traceback" not in said + err, err


def test_sub_of_a_quiet_topic_of_a_running_daemon_does_not_ask_whether_it_runs() -> None:
    # an idle skin publishes no contact: `sub contact` asked "is the daemon running?" of a
    # daemon whose health came every second. Its health says it runs: nothing to ask.
    with publisher() as endpoint:  # contact, health and raw; never topology
        out = run_subscriber([CLI, "sub", "topology", "--endpoint", endpoint, "--timeout", "7"])
    assert out.returncode == 1 and "no message for 7 s" in out.stderr, out.stderr
    assert "is the daemon running" not in out.stderr, out.stderr


def test_sub_refuses_a_topic_no_topic_starts_with() -> None:
    """`cellbridge sub helth` (or `contacts`) waited forever without a word: a prefix that
    matches none of the daemon's topics is refused, naming them; a true prefix still works."""
    with publisher() as endpoint:
        typo = run_subscriber([CLI, "sub", "contact", "helth", "--endpoint", endpoint, "--timeout", "20"])
        prefix = run_subscriber([CLI, "sub", "heal", "--endpoint", endpoint, "--count", "1", "--timeout", "20"])
    assert typo.returncode == 2 and typo.stdout == "" and "Traceback" not in typo.stderr
    assert "'helth'" in typo.stderr and "contact, element, raw, health, topology, serial" in typo.stderr
    assert prefix.returncode == 0 and [ln["topic"] for ln in json_lines(prefix.stdout)] == ["health"]


def test_sub_as_curve_client(tmp_path: Path) -> None:
    (tmp_path / "clients").mkdir()
    server_pub, server_secret = write_keypair(tmp_path, "server")
    write_keypair(tmp_path / "clients", "arm")
    write_keypair(tmp_path, "stranger")
    context = zmq.Context()
    curve = CurveServer(context, CurveKeys(server_secret, tmp_path / "clients"))
    try:
        with publisher(setup=curve.apply, context=context) as endpoint:
            common = [CLI, "sub", "contact", "--endpoint", endpoint, "--server-key", str(server_pub)]
            allowed = run_subscriber([*common, "--client-key", str(tmp_path / "clients" / "arm.key_secret"),
                                      "--count", "2", "--timeout", "20"])
            foreign = run_subscriber([*common, "--client-key", str(tmp_path / "stranger.key_secret"),
                                      "--timeout", "1.5"])
            plain = run_subscriber([CLI, "sub", "--endpoint", endpoint, "--timeout", "1.5"])
    finally:
        curve.stop()
        context.term()
    assert allowed.returncode == 0 and len(json_lines(allowed.stdout)) == 2
    assert foreign.returncode == 1 and foreign.stdout == ""
    assert plain.returncode == 1 and plain.stdout == ""


@pytest.mark.parametrize(("args", "message"), [
    (["--server-key", "server.key"], "go together"),
    (["--server-key", "missing.key", "--client-key", "missing.key_secret"], "cannot read a CURVE key"),
    (["--endpoint", "tcp://nowhere"], "tcp://nowhere"),
    (["--count", "-1"], "--count must be at least 1, got -1"),
    (["--count", "0"], "--count must be at least 1, got 0 (leave it out to run until Ctrl-C)"),
])
def test_sub_bad_input_gives_clear_errors(args: list[str], message: str, tmp_path: Path) -> None:
    out = run_subscriber([CLI, "sub", *args, "--timeout", "0.1"], cwd=tmp_path)
    assert out.returncode == 2 and message in out.stderr and "Traceback" not in out.stderr


msgpack_ints = st.integers(-2**63, 2**64 - 1)
msgpack_values = st.recursive(
    st.none() | st.booleans() | msgpack_ints | st.floats() | st.text() | st.binary(),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text() | msgpack_ints, inner, max_size=4),
    max_leaves=12)


@given(msgpack_values)
def test_any_msgpack_payload_becomes_strict_json(value: object) -> None:
    line = json.dumps(message_to_json([b"contact", msgpack.packb(value)]), allow_nan=False)
    assert json.loads(line)["topic"] == "contact"


def test_json_conversion_keeps_values() -> None:
    payload = {"v": 1, "t_host": 1.5, "f": math.nan, "b": b"\x00\xff", 7: [1, -2]}
    assert message_to_json([b"element", msgpack.packb(payload)])["payload"] == {
        "v": 1, "t_host": 1.5, "f": None, "b": "00ff", "7": [1, -2]}


def test_sub_ends_quietly_when_its_reader_goes_away() -> None:
    with publisher() as endpoint:
        out = run_subscriber(["bash", "-c", f"set -o pipefail; '{CLI}' sub --endpoint {endpoint} --timeout 20 "
                                            "| head -n 2"])
    assert out.returncode == 0, out.stderr  # pipefail: sub's own status
    assert len(json_lines(out.stdout)) == 2
    assert "Traceback" not in out.stderr and "BrokenPipe" not in out.stderr
