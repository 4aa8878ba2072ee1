"""The three views as real processes under hostile input and at their edges: odd payloads,
other sites' pages, escape sequences in the daemon's strings, two daemons on one stream,
and stopping. The daemon is a stand-in (fake_daemon.FakeDaemon) that publishes exactly
what each test says; the views connect to it over loopback ZeroMQ as to a daemon.
"""

from __future__ import annotations

import http.client
import json
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from typing import Any

import pytest
from websockets.typing import Origin, Subprotocol

from daemon_harness import CLI
from fake_daemon import FakeDaemon, grid_layout
from pty_terminal import PtyProgram, pty_program
from support.view_clients import WebPage, args, cell, foreign_sequences, server_view

FOXGLOVE = [Subprotocol("foxglove.sdk.v1")]


def element(seq: int, forces: dict[int, float], source: str = "robot:5560") -> dict[str, Any]:
    ids = sorted(forces)
    return {"v": 1, "seq": seq, "source": source, "bridge": ids, "force": [forces[b] for b in ids],
            "valid": [True] * len(ids), "touched": [forces[b] > 0 for b in ids], "status": [0] * len(ids),
            "t_sample": [float(seq)] * len(ids)}


def health(seq: int, source: str = "robot:5560", **extra: Any) -> dict[str, Any]:
    return {"v": 1, "seq": seq, "source": source, "uptime": float(seq), "links": {"gw": {"connected": True}}, **extra}


def http_status(port: int, host: str, path: str = "/") -> int:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.putrequest("GET", path, skip_host=True)
        conn.putheader("Host", host)
        conn.endheaders()
        return conn.getresponse().status
    finally:
        conn.close()


def upgrade_status(port: int, host: str, origin: str | None, path: str = "/") -> bytes:
    """The status line a server answers a WebSocket upgrade with (raw: any Host header)."""
    head = [f"GET {path} HTTP/1.1", f"Host: {host}", "Upgrade: websocket", "Connection: Upgrade",
            "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==", "Sec-WebSocket-Version: 13",
            "Sec-WebSocket-Protocol: foxglove.sdk.v1"]
    if origin is not None:
        head.append(f"Origin: {origin}")
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(("\r\n".join(head) + "\r\n\r\n").encode())
        data = b""
        while b"\r\n" not in data:
            chunk = s.recv(4096)
            if not chunk:
                break
            data += chunk
    return data.split(b"\r\n", 1)[0]


# ---- 2: other sites' pages and DNS rebinding ------------------------------------------------

def test_web_answers_only_its_own_page_and_its_own_names() -> None:
    """A WebSocket from http://evil.example was accepted and fed frames; GET / with
    Host: evil.example answered 200."""
    from websockets.exceptions import InvalidStatus

    with FakeDaemon() as fd, server_view("web", fd) as (web, port):
        assert http_status(port, "evil.example") == 403
        assert http_status(port, f"evil.example:{port}", "/static/app.js") == 403
        assert http_status(port, f"robot.local:{port}") == 403
        assert http_status(port, f"127.0.0.1:{port}") == 200
        assert http_status(port, f"localhost:{port}") == 200
        assert http_status(port, f"{socket.gethostname()}:{port}") == 200  # this machine's own name
        for origin in ("http://evil.example", f"http://evil.example:{port}", f"http://127.0.0.1:{port + 1}", "null"):
            with pytest.raises(InvalidStatus) as refused:
                WebPage(port, origin)
            assert refused.value.response.status_code == 403, origin
        assert upgrade_status(port, f"evil.example:{port}", f"http://evil.example:{port}", "/ws").startswith(
            b"HTTP/1.1 403")  # DNS rebinding: same-origin, but not a name of this server
        for page_origin in (f"http://127.0.0.1:{port}", None):  # the page itself; a program
            page = WebPage(port, page_origin)
            try:
                fd.publish("health", health(0))
                assert page.frame()["type"] == "frame"
            finally:
                page.close()


def test_web_answers_to_a_name_given_with_allow_host() -> None:
    with FakeDaemon() as fd, server_view("web", fd, "--allow-host", "robot.local") as (web, port):
        assert http_status(port, f"robot.local:{port}") == 200 and http_status(port, f"ROBOT.local.:{port}") == 200
        assert http_status(port, "evil.example") == 403
        assert upgrade_status(port, f"robot.local:{port}", f"http://robot.local:{port}", "/ws").startswith(
            b"HTTP/1.1 101")


def test_foxglove_admits_the_desktop_app_and_foxgloves_web_app_only() -> None:
    """cellbridge foxglove answered any Origin with serverInfo and advertise."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    with FakeDaemon() as fd, server_view("foxglove", fd) as (fx, port):
        for origin in ("http://evil.example", f"http://127.0.0.1:{port + 1}", "null"):
            with pytest.raises(InvalidStatus) as refused:
                with connect(f"ws://127.0.0.1:{port}", origin=Origin(origin), subprotocols=FOXGLOVE, open_timeout=10):
                    pass
            assert refused.value.response.status_code == 403, origin
        assert upgrade_status(port, f"evil.example:{port}", None).startswith(b"HTTP/1.1 403")
        for admitted in (None, Origin("https://app.foxglove.dev")):
            with connect(f"ws://127.0.0.1:{port}", origin=admitted, subprotocols=FOXGLOVE, open_timeout=10) as ws:
                assert json.loads(ws.recv(timeout=10))["op"] == "serverInfo"
    with FakeDaemon() as fd, server_view("foxglove", fd, "--allow-origin", "http://localhost:3000") as (fx, port):
        with connect(f"ws://127.0.0.1:{port}", origin=Origin("http://localhost:3000"), subprotocols=FOXGLOVE,
                     open_timeout=10) as ws:
            assert json.loads(ws.recv(timeout=10))["op"] == "serverInfo"


# ---- 1: one odd message neither freezes the page nor ends foxglove --------------------------

def _foxglove_elements(port: int, pred: Any, timeout: float = 20.0) -> dict[str, Any]:
    from cellbridge.views.foxglove import TOPICS
    from foxglove_client import FoxgloveClient

    client = FoxgloveClient(f"ws://127.0.0.1:{port}")
    try:
        client.wait_channels([TOPICS["elements"]])
        client.subscribe(TOPICS["elements"])
        return client.next_message(TOPICS["elements"], timeout=timeout, pred=pred)[1]
    finally:
        client.close()


def test_a_health_with_an_infinite_count_neither_freezes_the_page_nor_ends_foxglove() -> None:
    """pub.dropped.element = inf: the page got 0 frames after it (its picture frozen, still
    "live"), and foxglove exited with a traceback. Same for a layout spanning ±1e308."""
    with FakeDaemon() as fd, server_view("web", fd) as (web, wport), server_view("foxglove", fd) as (fx, fport):
        page = WebPage(wport)
        try:
            seq = 0
            end = time.monotonic() + 20
            while True:  # until both views hear the stream (a SUB joins a moment after it connects)
                fd.publish("element", element(seq, {1: 1.0}))
                seq += 1
                f = page.frame(timeout=5)
                if cell(f, 1) is not None or time.monotonic() > end:
                    break
            fd.publish("health", health(0, pub={"dropped": {"element": math.inf}}))
            fd.publish("topology", {"v": 1, "seq": 0, "source": "robot:5560",
                                    "layout": {"side": 0.04, "ids": [1, 2], "x": [-1e308, 1e308], "y": [0.0, 0.0]}})
            fd.publish("health", health(1, pub={"dropped": {"element": 1e308, "contact": 1e308}}))
            for k in range(30):  # the skin goes on being pressed: the views must show it
                fd.publish("element", element(seq + k, {1: 3.0}))
                time.sleep(0.02)
            f = page.frame(lambda f: (cell(f, 1) or {}).get("force") == 3.0 and f["counters"]["received"].get(
                "health", 0) >= 2)
            assert f["live"] and any("daemon dropped ?" in s for s in f["status"]), f["status"]
            got = _foxglove_elements(fport, lambda m: any(e["bridge"] == 1 and e["force"] == 3.0
                                                          for e in m["elements"]))
            assert got["elements"]
        finally:
            page.close()
        assert web.poll() is None and fx.poll() is None
        for p in (web, fx):
            p.send_signal(signal.SIGTERM)
            assert p.wait(10) == 0
            assert b"Traceback" not in p.stderr.read()  # type: ignore[union-attr]


# ---- 9: one source per picture ---------------------------------------------------------------

def _two_sources(fd: FakeDaemon, rounds: int = 40) -> None:
    """Two daemons on one stream (a proxy): robot:5560 presses bridge 5 with 1 N, robot:5562 with 4 N."""
    for seq in range(rounds):
        for src, f in (("robot:5560", 1.0), ("robot:5562", 4.0)):
            fd.publish("element", element(seq, {5: f, 1: 0.0}, src))
            fd.publish("health", health(seq, src, uptime=float(seq)))
        time.sleep(0.05)


def test_a_view_never_mixes_two_sources_into_one_picture() -> None:
    """The views ignored source: behind a proxy the element of two skins alternated on the page."""
    with FakeDaemon() as fd, server_view("web", fd) as (web, port):
        page = WebPage(port)
        try:
            seq = 0
            end = time.monotonic() + 20
            while time.monotonic() < end:  # robot:5560 alone, until the view hears it: the first source heard
                fd.publish("element", element(seq, {5: 1.0, 1: 0.0}, "robot:5560"))
                seq += 1
                f = page.frame()
                if cell(f, 5) is not None:
                    break
            for _ in range(10):  # then both, robot:5562 last: the picture stays robot:5560's
                n = f["counters"]["received"].get("element", 0)
                _two_sources(fd, 1)
                f = page.frame(lambda f, n=n: f["counters"]["received"].get("element", 0) >= n + 2)
                assert cell(f, 5)["force"] == 1.0  # type: ignore[index]
        finally:
            page.close()


def test_each_view_shows_only_the_source_it_is_given() -> None:
    with FakeDaemon() as fd, server_view("web", fd, "--source", "robot:5562") as (web, wport), \
            server_view("foxglove", fd, "--source", "robot:5562") as (fx, fport), \
            pty_program([CLI, "watch", *args(fd), "--source", "robot:5562"]) as watch:
        page = WebPage(wport)
        try:
            _two_sources(fd, 10)
            picked = page.frame(lambda f: cell(f, 5) is not None and f["counters"]["other_sources"] > 5)
            assert cell(picked, 5)["force"] == 4.0  # type: ignore[index]
            assert any("source: robot:5562; not shown: robot:5560" in s for s in picked["status"]), picked["status"]
            for _ in range(5):
                _two_sources(fd, 2)
                assert cell(page.frame(), 5)["force"] == 4.0  # type: ignore[index]
        finally:
            page.close()
        got = _foxglove_elements(fport, lambda m: any(e["bridge"] == 5 for e in m["elements"]))
        assert [e["force"] for e in got["elements"] if e["bridge"] == 5] == [4.0]
        _two_sources(fd, 20)
        watch.wait_for(r"not shown: robot:5560")
        watch.wait_for(r"4\.0N")
        assert "1.0N" not in watch.text()


# ---- 3: the daemon's strings never reach the terminal raw --------------------------------------

OSC52 = "\x1b]52;c;cHduZWQ=\x07"  # write "pwned" to the clipboard
RED = "\x1b[31m"  # basic red: never emitted by the view (truecolor styles)


def test_watch_shows_the_daemons_control_characters_escaped() -> None:
    """A link name, the calibration status and a tare error reached the terminal raw: an
    OSC 52 clipboard write and a CSI colour arrived at the pty."""
    def reply(req: Any) -> Any:
        rid = req.get("id") if isinstance(req, dict) else None
        if isinstance(req, dict) and req.get("cmd") == "tare":
            return {"v": 1, "id": rid, "ok": False, "error": f"no{OSC52}pe{RED}"}
        return {"v": 1, "id": rid, "ok": True, "layout": grid_layout()}

    shown = (re.escape("\\x1b]52;c;cHduZWQ=\\x07:up"), re.escape("calibration \\x1b[31m9 ready"))
    with FakeDaemon(reply=reply) as fd, pty_program([CLI, "watch", *args(fd)]) as watch:
        # published until the view shows both (a loaded machine may start it after a fixed
        # number of messages went out: a subscriber misses what came before it joined)
        end = time.monotonic() + 60
        seq = 0
        while time.monotonic() < end and not all(re.search(p, watch.text()) for p in shown):
            fd.publish("health", health(seq, links={OSC52: {"connected": True}},
                                        layout={"calibration": {"ready": f"{RED}9", "collecting": 0}}))
            fd.publish("element", element(seq, {1: 1.0}))
            seq += 1
            time.sleep(0.05)
        for p in shown:
            watch.wait_for(p, timeout=1)
        watch.send(b"t")
        watch.wait_for("re-take the baseline")
        watch.send(b"y")
        watch.wait_for(re.escape("tare refused: no\\x1b]52;c;cHduZWQ=\\x07pe\\x1b[31m"))
        text = watch.text()
    assert OSC52 not in text and RED not in text
    assert foreign_sequences(text) == []


# ---- 12: stopping -------------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["web", "foxglove"])
@pytest.mark.parametrize("signals", [1, 2])
def test_a_view_closes_its_clients_and_exits_at_once_on_sigterm(kind: str, signals: int) -> None:
    """web took 5–16 s to exit with a page open (waiting out the page's WebSocket) and sent
    no close frame; foxglove printed a CancelledError traceback and sent no close frame; a
    second SIGTERM ended web with a traceback."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    with FakeDaemon() as fd, server_view(kind, fd) as (view, port):
        url = f"ws://127.0.0.1:{port}" + ("/ws" if kind == "web" else "")
        with connect(url, subprotocols=FOXGLOVE if kind == "foxglove" else None,
                     open_timeout=10, max_size=1 << 26) as ws:
            fd.publish("health", health(0))
            ws.recv(timeout=10)
            t0 = time.monotonic()
            for _ in range(signals):
                view.send_signal(signal.SIGTERM)
                time.sleep(0.05)
            with pytest.raises(ConnectionClosed) as closed:
                while True:
                    ws.recv(timeout=10)
            received = closed.value.rcvd  # the close frame the view sent (None: dropped without one)
            rc = view.wait(10)
            took = time.monotonic() - t0
        stderr = view.stderr.read().decode()  # type: ignore[union-attr]
    assert received is not None, "the client got no close frame"
    if kind == "web":
        assert received.code == 1001  # going away
    assert rc == 0 and "Traceback" not in stderr and "Error" not in stderr, stderr
    assert took < 3.0, f"{kind} took {took:.1f} s to exit"  # about 0.3 s; bench/bench_view_stop.py measures it


@pytest.mark.parametrize("how", ["SIGTERM", "SIGTERM twice", "Ctrl-C"])
def test_watch_ends_on_sigterm_and_ctrl_c_with_the_terminal_restored(how: str) -> None:
    """SIGTERM killed watch at once, its terminal left in the alternate screen."""
    with FakeDaemon() as fd:
        watch = PtyProgram([CLI, "watch", *args(fd)])
        try:
            fd.publish("health", health(0))
            watch.wait_for("this view")
            t0 = time.monotonic()
            if how == "Ctrl-C":
                watch.send(b"\x03")
            else:
                for _ in range(2 if "twice" in how else 1):
                    os.killpg(watch.proc.pid, signal.SIGTERM)
                    time.sleep(0.05)
            rc = watch.proc.wait(10)
            took = time.monotonic() - t0
        finally:
            watch.stop()  # (the reader takes every byte written before the exit)
        text = watch.text()
    assert rc == 0 and "Traceback" not in text
    assert text.rfind("\x1b[?1049l") > text.rfind("\x1b[?1049h") >= 0  # back from the alternate screen
    assert took < 3.0, f"watch took {took:.1f} s to exit"


HANGING_STOP = """
import sys, threading
from cellbridge.views.signals import on_stop_signal
on_stop_signal(lambda: None, deadline=0.5, restore=lambda: open(sys.argv[1], "w").write("restored"))
print("ready", flush=True)
threading.Event().wait()  # a stop that never ends: the main thread blocked, as in a stuck shutdown
"""


def test_a_view_whose_stop_hangs_is_cut_off_after_the_deadline(tmp_path: Any) -> None:
    """A view stuck in its shutdown ignored every later SIGTERM and outlived the suite."""
    marker = tmp_path / "restored"
    proc = subprocess.Popen([sys.executable, "-c", HANGING_STOP, str(marker)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline() == b"ready\n"
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.1)
        proc.send_signal(signal.SIGTERM)  # ignored: the stop under way goes on
        rc = proc.wait(20)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5)
    stderr = proc.stderr.read().decode()  # type: ignore[union-attr]
    assert rc == 1 and "still stopping 0.5 s after SIGTERM" in stderr, (rc, stderr)
    assert marker.read_text() == "restored"


# ---- 14: the page's contact label leaves the elements' own text readable ------------------------

RECORD_TEXT = """(() => {
  window.__texts = [];
  const fill = CanvasRenderingContext2D.prototype.fillText;
  const clear = CanvasRenderingContext2D.prototype.clearRect;
  CanvasRenderingContext2D.prototype.clearRect = function (...a) {
    if (this.canvas.id === "skin") window.__texts = [];
    return clear.apply(this, a);
  };
  CanvasRenderingContext2D.prototype.fillText = function (text, x, y, ...rest) {
    if (this.canvas.id === "skin") {
      const m = this.measureText(text);  // the ink's box around the point drawn at
      window.__texts.push({text: String(text), x0: x - m.actualBoundingBoxLeft, x1: x + m.actualBoundingBoxRight,
                           y0: y - m.actualBoundingBoxAscent, y1: y + m.actualBoundingBoxDescent});
    }
    return fill.call(this, text, x, y, ...rest);
  };
  return true;
})()"""


@pytest.mark.skipif(shutil.which("chromium") is None, reason="Debian's chromium is not installed")
@pytest.mark.parametrize("x, y", [(0.040, 0.022), (0.060, 0.028), (0.020, 0.040), (0.100, 0.110), (0.052, 0.030)])
def test_the_pages_contact_label_is_never_drawn_over_an_elements_id_or_force(x: float, y: float,
                                                                            tmp_path: Any) -> None:
    """The contact's label was drawn over the force and id of the element beside it."""
    from browser import browser

    forces = {b: 2.0 for b in range(1, 10)}
    with FakeDaemon() as fd, server_view("web", fd) as (web, port), browser(tmp_path) as page:
        page.navigate(f"http://127.0.0.1:{port}/")
        page.wait_for("window.cellbridge && cellbridge.connects === 1", what="the page's connection")
        page.evaluate(RECORD_TEXT)
        end = time.monotonic() + 30
        texts: list[dict[str, Any]] = []
        seq = 0
        while time.monotonic() < end:
            fd.publish("element", element(seq, forces))
            fd.publish("contact", {"v": 1, "seq": seq, "source": "robot:5560", "t_sample": 1.0, "contacts": [
                {"id": 7, "x": x, "y": y, "force": 2.0, "diameter": 0.010, "observable": [True, True]}]})
            seq += 1
            time.sleep(0.1)
            texts = page.evaluate("window.__texts")
            if any(t["text"].startswith("#7 ") for t in texts) and sum(t["text"] == "2.0N" for t in texts) == 9:
                break
        labels = [t for t in texts if t["text"].startswith("#")]
        own = [t for t in texts if not t["text"].startswith("#")]
        assert len(labels) == 1 and len(own) == 18, texts  # 9 ids, 9 forces, one contact label

        def overlap(a: dict[str, float], b: dict[str, float]) -> bool:
            return a["x0"] < b["x1"] and b["x0"] < a["x1"] and a["y0"] < b["y1"] and b["y0"] < a["y1"]

        assert [t["text"] for t in own if overlap(labels[0], t)] == [], (labels[0], own)


def test_a_stop_cut_off_leaves_the_terminals_stderr_as_it_was(tmp_path: Any) -> None:
    """The cut-off's line went out with O_NONBLOCK set on stderr, and left it set: that flag
    belongs to the open file of the terminal, which the shell that started the view shares,
    so the shell and every program after it found their terminal non-blocking (reads
    failing with EAGAIN, 'Resource temporarily unavailable')."""
    import fcntl
    import pty

    master, slave = pty.openpty()
    try:
        assert not fcntl.fcntl(slave, fcntl.F_GETFL) & os.O_NONBLOCK
        proc = subprocess.Popen([sys.executable, "-c", HANGING_STOP, str(tmp_path / "restored")],
                                stdout=subprocess.PIPE, stderr=slave, start_new_session=True)
        try:
            assert proc.stdout is not None and proc.stdout.readline() == b"ready\n"
            proc.send_signal(signal.SIGTERM)
            rc = proc.wait(20)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(5)
        assert rc == 1
        assert b"still stopping" in os.read(master, 4096)
        assert not fcntl.fcntl(slave, fcntl.F_GETFL) & os.O_NONBLOCK, "the terminal was left non-blocking"
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.parametrize("command", [["web", "--port", "-1"], ["foxglove", "--port", "-1"],
                                     ["foxglove", "--port", "70000"]])
def test_a_view_given_a_port_out_of_range_says_so(command: list[str]) -> None:
    # `cellbridge foxglove --port -1` ended in "OverflowError: bind(): port must be 0-65535."
    r = subprocess.run([CLI, *command], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--port must be within 0..65535" in r.stderr and "Traceback" not in r.stderr, r.stderr


@pytest.mark.parametrize(("command", "option"), [
    (["web", "--port", "0"], "--endpoint"), (["foxglove", "--port", "0"], "--control"),
    (["ros2"], "--endpoint"), (["record", "{tmp}/bag", "--profile", "ros2", "--duration", "1"], "--control"),
])
def test_a_view_given_an_endpoint_without_its_scheme_says_so(command: list[str], option: str, tmp_path: Any) -> None:
    """`cellbridge web --endpoint 127.0.0.1:5560` (tcp:// left out) printed libzmq's traceback:
    a sentence naming the option now, exit 2, nothing left running."""
    cmd = [CLI, *(c.format(tmp=tmp_path) for c in command), option, "127.0.0.1:5560"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=60, start_new_session=True)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert f"{option} 127.0.0.1:5560: Invalid argument: not an endpoint to connect to" in r.stderr


def test_watch_says_when_no_daemon_answers_and_not_when_one_runs_quietly() -> None:
    # `cellbridge watch` with no daemon showed "waiting for the first message" for ever; as
    # `cellbridge sub` does, after 5 s with nothing, not even health, it says no daemon answers
    from daemon_harness import free_port

    nobody = f"tcp://127.0.0.1:{free_port()}"
    with pty_program([CLI, "watch", "--endpoint", nobody, "--control", f"tcp://127.0.0.1:{free_port()}"]) as watch:
        watch.wait_for("waiting for the first message")
        start = time.monotonic()
        watch.wait_for("no daemon answers on " + re.escape(nobody), timeout=30)
        assert time.monotonic() - start > 3.0  # not at once: a daemon takes a moment to be heard
        watch.wait_for("not even its health")
        assert watch.proc.poll() is None  # it waits on: a daemon started later is shown
        watch.send(b"\x03")
        assert watch.proc.wait(10) == 0
    with FakeDaemon() as fd, pty_program([CLI, "watch", *args(fd)]) as watch:  # only health, once a second
        end = time.monotonic() + 7.0
        seq = 0
        while time.monotonic() < end:
            fd.publish("health", health(seq))
            seq += 1
            time.sleep(0.5)
        watch.wait_for("daemon: live")
        assert "no daemon answers" not in watch.text()
