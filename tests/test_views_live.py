"""The three views against a live daemon fed by a known press, as real processes.

The daemon reads synthesized gateway traffic of a 3×3 skin from a pty (view_harness):
a 2 N press across the seam of bridges 2 and 5. Each view must show what the daemon
published: the terminal view in tmux (``capture-pane``), the page in headless Chromium
(its pixels and its text), the Foxglove server to a protocol client (decoded with the
advertised schemas). Pictures for the README are written where ``CELLBRIDGE_PICTURES``
points (``CELLBRIDGE_PICTURES=docs/img make test``).
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import shutil
import signal
import socket
import struct
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from browser import CHROMIUM, browser
from cellbridge.views.model import level_rgb
from support.view_clients import PICTURES, picture, pixel
from view_harness import CLI, PRESSED, Client, daemon, fed_skin, free_port, skin_config, view_process, wait_ready

TMUX = shutil.which("tmux")
needs_tmux = pytest.mark.skipif(TMUX is None, reason="tmux is not installed (make test installs it with apt-get as root)")
needs_chromium = pytest.mark.skipif(CHROMIUM is None,
                                    reason="Debian's chromium is not installed (make test installs it with apt-get as root)")


class Published:
    """What the daemon publishes, newest per topic, read by the test as one more subscriber."""

    def __init__(self, client: Client) -> None:
        self.client = client
        self.last: dict[str, dict[str, Any]] = {}

    def update(self, seconds: float = 0.3) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            got = self.client.recv(0.05)
            if got is not None:
                self.last[got[0]] = got[1]

    def contact(self) -> dict[str, Any]:
        c = self.client.wait_for("contact", lambda m: len(m["contacts"]) == 1, timeout=60)
        return c["contacts"][0]

    def force(self, bridge: int) -> float:
        m = self.client.wait_for("element", lambda m: bridge in m["bridge"], timeout=10)
        return m["force"][m["bridge"].index(bridge)]


Live = tuple[dict[str, str], Any, Published, Path]


@contextmanager
def _pressed_daemon(tmp_path: Path) -> Iterator[Live]:
    """A daemon on a pty fed by a held press, its first contact already published."""
    with fed_skin(tmp_path) as (pty, feeder):
        cfg, ep = skin_config(tmp_path, pty)
        client = Client(ep, (b"contact", b"element", b"health"))
        try:
            with daemon(cfg, tmp_path / "daemon.log"):
                wait_ready(client)
                feeder.press()
                pub = Published(client)
                pub.contact()  # the first estimate (the contact worker may compile its kernels first)
                yield ep, feeder, pub, cfg
        finally:
            client.close()


@pytest.fixture(scope="module")
def _shared_daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Live, Any]]:
    """One pressed daemon for the module's tests that only watch it: starting one, taking
    its baseline and waiting for its first estimate took seconds per test. They change
    nothing it holds (they start views, connect and go; the tare, which re-baselines it,
    has a daemon of its own: :func:`own_live`). Also its subscriber, which :func:`live`
    drains for each test."""
    with _pressed_daemon(tmp_path_factory.mktemp("views_live")) as shared:
        yield shared, shared[2].client


@pytest.fixture
def live(_shared_daemon: tuple[Live, Any]) -> Live:
    """The module's pressed daemon, as a test that started it would see it: what it
    published before this test (queued at the test's subscriber, which keeps every
    message) is dropped and the newest per topic forgotten, so every check reads what the
    daemon publishes now, under the press still held."""
    shared, client = _shared_daemon
    ep, feeder, pub, _ = shared
    assert feeder.is_alive() and feeder.pattern is not None, "the shared skin's feeder stopped or released its press"
    client.request({"v": 1, "cmd": "ping"})  # the daemon still answers (it did not die in an earlier test)
    while client.recv(0.0) is not None:
        pass
    pub.last.clear()
    pub.contact()  # the held press's contact, published after this test began
    return shared


@pytest.fixture
def own_live(tmp_path: Path) -> Iterator[Live]:
    """A pressed daemon of the test's own: for a test that changes what the daemon holds."""
    with _pressed_daemon(tmp_path) as fresh:
        yield fresh


def view_args(ep: dict[str, str]) -> list[str]:
    return ["--endpoint", ep["pub"], "--control", ep["control"]]


CONTACT_LINE = re.compile(r"#(\d+)\s+x (~?[\d.]+).*?\s+y (~?[\d.]+).*?F ([\d.]+) N\s+⌀ ([\d.]+) mm")


def assert_contact_shown(text: str, published: dict[str, Any]) -> None:
    m = CONTACT_LINE.search(text)
    assert m, text
    cid, x, y, force, diameter = m.groups()
    assert int(cid) == published["id"]
    assert float(x.lstrip("~")) == pytest.approx(published["x"] * 1e3, abs=0.3)
    assert float(y.lstrip("~")) == pytest.approx(published["y"] * 1e3, abs=0.3)
    assert float(force) == pytest.approx(published["force"], abs=0.03)
    assert float(diameter) == pytest.approx(published["diameter"] * 1e3, abs=0.2)


# ---- cellbridge watch in tmux ---------------------------------------------------------------

class Tmux:
    def __init__(self, tmp_path: Path) -> None:
        self.sock = str(tmp_path / "tmux.sock")

    def __call__(self, *args: str) -> str:
        return subprocess.run([TMUX, "-S", self.sock, *args], capture_output=True, text=True, timeout=20).stdout  # type: ignore[list-item]  # TMUX was found, or the test skipped

    def capture(self, colour: bool = False) -> str:
        return self("capture-pane", "-p", *(["-e"] if colour else []), "-t", "v")

    def wait_for(self, pattern: str, timeout: float = 30.0) -> str:
        end = time.monotonic() + timeout
        screen = ""
        while time.monotonic() < end:
            screen = self.capture()
            if re.search(pattern, screen):
                return screen
            time.sleep(0.1)
        raise AssertionError(f"the terminal never showed {pattern!r}:\n{screen}")

    def kill(self) -> None:
        self("kill-server")


@needs_tmux
def test_watch_shows_the_pressed_elements_force_and_the_contact_and_q_quits(live: Any, tmp_path: Path) -> None:
    ep, feeder, pub, _ = live
    tmux = Tmux(tmp_path)
    try:
        status = tmp_path / "watch.status"
        tmux("new-session", "-d", "-s", "v", "-x", "80", "-y", "24", "-e", "COLORTERM=truecolor",
             f"{CLI} watch {' '.join(view_args(ep))}; echo $? > {status}")
        tmux.wait_for(r"#\d+ ")
        time.sleep(0.5)  # a few refreshes on the held press
        screen = tmux.capture()
        pub.update()
        assert_contact_shown(screen, pub.contact())
        lines = screen.splitlines()
        labels = {}
        for b in PRESSED:  # each pressed element's cell carries its force
            label = f"{pub.force(b):.1f}N"
            where = [(r, line.index(label)) for r, line in enumerate(lines[:14]) if label in line]
            assert where, f"no cell shows {label} for bridge {b}:\n{screen}"
            labels[b] = where[0]
        # bridge 5 lies above bridge 2 (y up), in the same column of elements
        assert labels[5][0] < labels[2][0] and abs(labels[5][1] - labels[2][1]) <= 2, labels
        assert re.search(r"bridges: 9 alive, 0 silent", screen) and "lost 0" in screen, screen
        coloured = tmux.capture(colour=True)
        for b, (row, _) in labels.items():  # the label's row is painted in the force's colour
            want = level_rgb(pub.force(b) / 5.0)
            got = [tuple(map(int, m)) for m in re.findall(r"48;2;(\d+);(\d+);(\d+)", coloured.splitlines()[row])]
            assert any(all(abs(g - w) <= 3 for g, w in zip(c, want)) for c in got), (b, want, got)
        _terminal_picture(coloured)
        tmux("send-keys", "-t", "v", "q")
        end = time.monotonic() + 15
        while not status.exists() or not status.read_text().strip():
            assert time.monotonic() < end, "watch did not exit on q"
            time.sleep(0.1)
        assert status.read_text().strip() == "0"
    finally:
        tmux.kill()


def _terminal_picture(ansi: str) -> None:
    """The terminal view as an SVG for the README (rich renders the captured ANSI screen)."""
    if not PICTURES:
        return
    from rich.console import Console
    from rich.text import Text

    console = Console(record=True, width=80, file=io.StringIO(), color_system="truecolor")
    console.print(Text.from_ansi(ansi.rstrip("\n")), crop=True, overflow="crop")
    picture("watch.svg", console.export_svg(title="cellbridge watch").encode())


@needs_tmux
def test_watch_tares_only_after_confirmation(own_live: Any, tmp_path: Path) -> None:
    ep, feeder, pub, _ = own_live  # its tare re-baselines the daemon: not the module's shared one
    tmux = Tmux(tmp_path)
    try:
        tmux("new-session", "-d", "-s", "v", "-x", "80", "-y", "24", f"{CLI} watch {' '.join(view_args(ep))}")
        tmux.wait_for(r"#\d+ ")
        tmux("send-keys", "-t", "v", "t")
        tmux.wait_for("re-take the baseline")
        tmux("send-keys", "-t", "v", "n")
        tmux.wait_for("tare: cancelled")
        pub.update()
        assert pub.last["health"]["layout"]["calibration"]["collecting"] == 0  # nothing was tared
        tmux("send-keys", "-t", "v", "t")
        tmux.wait_for("re-take the baseline")
        tmux("send-keys", "-t", "v", "y")
        tmux.wait_for(r"tare: 9 elements re-baselining")
    finally:
        tmux.kill()


@needs_tmux
def test_watch_of_a_replay_says_its_tare_went_unanswered(tmp_path: Path) -> None:
    # A replay publishes the daemon's topics and has no control socket: the tare was queued
    # for a daemon that is not there, and the status line said "tare: sent" for ever.
    from cellbridge.recording import codec
    from cellbridge.recording.mcapfile import RecordingWriter
    from support.pub_helpers import daemon_messages

    rec = tmp_path / "skin.mcap"
    writer = RecordingWriter(rec, fsync=False)
    t0 = time.time_ns()
    for i in range(1200):  # two minutes of the daemon's topics at 10 Hz
        for topic, payload in daemon_messages(i):
            writer.add(topic, codec.encode(topic, payload), t0 + i * 100_000_000, t0 + i * 100_000_000, i)
    writer.finish()
    pub, control = f"tcp://127.0.0.1:{free_port()}", f"tcp://127.0.0.1:{free_port()}"  # nothing on control
    replay = subprocess.Popen([CLI, "replay", str(rec), "--endpoint", pub], stderr=subprocess.PIPE,
                              start_new_session=True)
    tmux = Tmux(tmp_path)
    try:
        tmux("new-session", "-d", "-s", "v", "-x", "80", "-y", "24",
             f"{CLI} watch --endpoint {pub} --control {control}")
        tmux.wait_for("#3 ")  # the replayed contact
        tmux("send-keys", "-t", "v", "t")
        tmux.wait_for("re-take the baseline")
        tmux("send-keys", "-t", "v", "y")
        screen = tmux.wait_for(r"tare: (not sent|no answer)", timeout=15)
        assert control in screen and "tare: sent" not in screen, screen
    finally:
        tmux.kill()
        os.killpg(replay.pid, signal.SIGTERM)
        replay.communicate(timeout=15)


def test_a_tare_no_daemon_took_is_never_delivered_later_and_one_unanswered_says_so() -> None:
    # The view's control socket queued a tare for a control endpoint nobody served: a daemon
    # started there later would have re-baselined on it, long after the user asked.
    import msgpack
    import zmq

    from cellbridge.views import source as source_module
    from cellbridge.views.model import SkinView
    from cellbridge.views.source import Source

    control = f"tcp://127.0.0.1:{free_port()}"
    src = Source(f"tcp://127.0.0.1:{free_port()}", control)
    context = zmq.Context()
    router = context.socket(zmq.ROUTER)
    router.linger = 0
    try:
        src.tare()
        assert src.notice.startswith("tare: not sent") and control in src.notice, src.notice
        router.bind(control)  # a daemon's control socket appears, and answers nothing
        model = SkinView()
        asked: list[str] = []
        end = time.monotonic() + 10
        while time.monotonic() < end and not asked:  # until the view is connected: its layout requests come
            src.drain(model)
            asked += [msgpack.unpackb(router.recv_multipart()[-1])["cmd"] for _ in range(1) if router.poll(100)]
        src.tare()
        while router.poll(500):
            asked.append(msgpack.unpackb(router.recv_multipart()[-1])["cmd"])
        assert asked.count("tare") == 1 and asked[-1] == "tare", asked  # the one sent once connected, not the first
        assert src.notice == "tare: sent"
        end = time.monotonic() + source_module.TARE_ANSWER_S + 5
        while time.monotonic() < end and src.notice == "tare: sent":
            src.drain(model)
            time.sleep(0.1)
        assert src.notice.startswith(f"tare: no answer from {control}"), src.notice
    finally:
        router.close()
        context.term()
        src.close()


# ---- cellbridge web in headless Chromium ----------------------------------------------------

def start_web(ep: dict[str, str], *extra: str) -> tuple[Any, str]:
    port = free_port()
    return ["web", "--port", str(port), *view_args(ep), *extra], f"http://127.0.0.1:{port}/"


def wait_line(proc: subprocess.Popen[bytes], timeout: float = 30.0) -> str:
    assert proc.stdout is not None
    import select

    ready, _, _ = select.select([proc.stdout], [], [], timeout)
    assert ready, "the view printed nothing"
    return proc.stdout.readline().decode()


@needs_chromium
def test_web_page_colours_the_pressed_elements_and_labels_the_contact(live: Any, tmp_path: Path) -> None:
    ep, feeder, pub, _ = live
    argv, url = start_web(ep)
    with view_process(argv, stdout=subprocess.PIPE) as web, browser(tmp_path) as page:
        assert wait_line(web).strip() == f"cellbridge web: {url}"
        page.navigate(url)
        page.wait_for("!!document.querySelector('#contacts li[data-id]')", what="a contact")
        time.sleep(0.5)
        pub.update()
        published = pub.contact()
        forces = {b: pub.force(b) for b in (*PRESSED, 9)}
        text = page.evaluate("document.querySelector('#contacts').textContent")
        png = page.screenshot(tmp_path / "web.png")
        assert_contact_shown(text, published)
        for b, f in forces.items():
            rect = page.evaluate(f"cellbridge.elementRect({b})")
            got = pixel(png, rect["x"] + 0.88 * rect["w"], rect["y"] + 0.6 * rect["h"])  # clear of labels and disk
            want = level_rgb((f if math.isfinite(f) else 0.0) / 5.0)
            assert all(abs(g - w) <= 8 for g, w in zip(got, want)), (b, f, got, want)
        assert pixel(png, *_centre(page.evaluate(f"cellbridge.elementRect({PRESSED[1]})"))) != level_rgb(0.0)
        # the contact disk is drawn where the daemon put it: its label on the canvas too
        frame = page.evaluate("cellbridge.frame.contacts[0]")
        assert frame["id"] == published["id"] and frame["label"].startswith(f"#{published['id']} ")
        # click an element: its force over time is plotted
        r5 = page.evaluate("cellbridge.elementRect(5)")
        page.call("Input.dispatchMouseEvent", type="mousePressed", x=r5["x"] + 5, y=r5["y"] + 5, button="left",
                  clickCount=1)
        page.call("Input.dispatchMouseEvent", type="mouseReleased", x=r5["x"] + 5, y=r5["y"] + 5, button="left",
                  clickCount=1)
        page.wait_for("cellbridge.select === 5 && cellbridge.series.length > 20", what="the plot of bridge 5")
        series = page.evaluate("cellbridge.series.slice(-10).map(p => p[1])")
        assert all(v == pytest.approx(forces[5], abs=0.05) for v in series), series
        time.sleep(0.3)
        picture("web.png", page.screenshot())  # the frame rate is bench/bench_views.py's to measure


def _centre(rect: dict[str, float]) -> tuple[float, float]:
    return rect["x"] + 0.88 * rect["w"], rect["y"] + 0.6 * rect["h"]


@needs_chromium
def test_web_page_recovers_after_the_daemon_restarts(tmp_path: Path) -> None:
    with fed_skin(tmp_path) as (pty, feeder):
        cfg, ep = skin_config(tmp_path, pty)
        client = Client(ep, (b"contact", b"health"))
        argv, url = start_web(ep)
        try:
            with view_process(argv, stdout=subprocess.PIPE) as web, browser(tmp_path) as page:
                wait_line(web)
                page.navigate(url)
                for run in (1, 2):
                    with daemon(cfg, tmp_path / f"daemon{run}.log"):
                        wait_ready(client)
                        feeder.press()
                        client.wait_for("contact", lambda m: len(m["contacts"]) == 1, timeout=60)
                        page.wait_for(f"cellbridge.frame && cellbridge.frame.live && cellbridge.frame.contacts.length"
                                      f" && cellbridge.frame.counters.daemon_restarts === {run - 1}",
                                      timeout=30, what=f"the contact from daemon run {run}")
                        # the page lists the contact this daemon publishes (its id: a press's onset
                        # may briefly show as a second track on a loaded machine, so the newest)
                        pub, shown = Published(client), ""
                        end = time.monotonic() + 20
                        while time.monotonic() < end:
                            pub.update(0.2)
                            ids = [c["id"] for c in pub.last.get("contact", {}).get("contacts", [])]
                            shown = page.evaluate("document.querySelector('#contacts').textContent")
                            if ids and shown.startswith(f"#{ids[0]} "):
                                break
                        else:
                            raise AssertionError(f"page shows {shown!r}, the daemon publishes ids {ids}")
                        feeder.press(None)  # the next daemon takes its baseline on a quiet skin
                    page.wait_for("document.getElementById('conn').textContent === 'daemon silent'",
                                  timeout=20, what="that the daemon is gone")
                assert page.evaluate("cellbridge.connects") == 1  # the page's own connection never broke
        finally:
            client.close()


@needs_chromium
def test_web_page_reconnects_after_the_page_server_restarts(live: Any, tmp_path: Path) -> None:
    ep, feeder, pub, _ = live
    argv, url = start_web(ep)
    with browser(tmp_path) as page:
        for run in (1, 2):
            with view_process(argv, stdout=subprocess.PIPE) as web:
                wait_line(web)
                if run == 1:
                    page.navigate(url)
                page.wait_for(f"cellbridge.connects === {run} && cellbridge.frame && cellbridge.frame.contacts.length",
                              timeout=30, what=f"connection {run} with the contact")


def test_web_beyond_loopback_answers_only_with_the_token(live: Any, tmp_path: Path) -> None:
    import urllib.error
    import urllib.request

    ep, *_ = live
    token = "k" * 24
    (tmp_path / "token").write_text(token + "\n")
    port = free_port()
    # 127.0.0.2 is loopback too, but --token-file makes any host protected: checked the same way
    with view_process(["web", "--port", str(port), "--token-file", str(tmp_path / "token"), *view_args(ep)],
                      stdout=subprocess.PIPE) as web:
        assert f"?token={token}" in wait_line(web)
        with pytest.raises(urllib.error.HTTPError) as denied:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5)
        assert denied.value.code == 403
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/?token={token}", timeout=5) as r:
            body = r.read().decode()
        assert "static/app.js" in body and "http" not in body.split("<body>")[1].replace("http-equiv", "")  # no CDN


# ---- cellbridge foxglove to a Foxglove protocol client --------------------------------------

@pytest.mark.parametrize("subprotocol", ["foxglove.websocket.v1", "foxglove.sdk.v1"])
def test_foxglove_advertises_and_sends_the_grid_and_contacts_as_published(own_live: Any, subprotocol: str) -> None:
    """A client speaking the protocol under either name (the issue's foxglove.websocket.v1,
    or foxglove.sdk.v1 as today's Foxglove app) gets it and the same channels."""
    from cellbridge.views.foxglove import TOPICS
    from foxglove_client import FoxgloveClient

    # A daemon of its own, its press just begun: on the module's shared daemon (its press
    # held for a minute), beside four CPU burners, the first grid once showed a pressed
    # element's force unknown (NaN); not yet understood, so not shared.
    ep, feeder, pub, _ = own_live
    port = free_port()
    with view_process(["foxglove", "--port", str(port), *view_args(ep)], stdout=subprocess.PIPE) as fx:
        assert wait_line(fx).strip() == f"cellbridge foxglove: ws://127.0.0.1:{port} (Foxglove WebSocket)"
        client = FoxgloveClient(f"ws://127.0.0.1:{port}", [subprotocol])
        try:
            assert client.subprotocol == subprotocol
            client.wait_channels(list(TOPICS.values()))
            grid_ch, scene_ch = client.by_topic(TOPICS["grid"]), client.by_topic(TOPICS["scene"])
            assert grid_ch is not None and scene_ch is not None
            assert (grid_ch["encoding"], grid_ch["schemaName"]) == ("protobuf", "foxglove.Grid")
            assert (scene_ch["encoding"], scene_ch["schemaName"]) == ("protobuf", "foxglove.SceneUpdate")
            assert all((client.by_topic(TOPICS[k]) or {}).get("encoding") == "json" for k in ("elements", "health", "contacts"))
            for k in ("grid", "scene", "elements", "health"):
                client.subscribe(TOPICS[k])
            pub.update()
            published = pub.contact()
            forces = {b: pub.force(b) for b in range(1, 10)}
            _, grid = client.next_message(TOPICS["grid"])
            _, scene = client.next_message(TOPICS["scene"], pred=lambda s: len(s.entities) == 1)
            _, elements = client.next_message(TOPICS["elements"])
            _, health = client.next_message(TOPICS["health"])
        finally:
            client.close()
    # the grid: 3 columns of 40 mm cells from the corner of the skin, force first
    assert grid.column_count == 3 and grid.cell_size.x == pytest.approx(0.04) and grid.frame_id == "skin"
    assert [f.name for f in grid.fields] == ["force", "dc1"] and grid.cell_stride == 8 and grid.row_stride == 24
    assert (grid.pose.position.x, grid.pose.position.y) == pytest.approx((-0.02, -0.02))
    values = struct.unpack(f"<{len(grid.data) // 4}f", grid.data)
    for b, f in forces.items():
        i = (b - 1) // 3 * 3 + (b - 1) % 3  # bridge ids run along rows from the corner
        shown = values[2 * i]
        if math.isfinite(f):
            assert shown == pytest.approx(f, abs=0.03), (b, shown, f)
        else:  # no force: an untouched element's 0 N, or unknown while its reading is not finite
            assert math.isnan(shown) or shown == 0.0, (b, shown, f)
    # the scene: old entities cleared, one disk for the contact, sized by its diameter, labelled with its id
    assert scene.deletions[0].type == 1  # ALL
    (entity,) = scene.entities
    (disk,) = entity.cylinders
    assert entity.id == f"contact-{published['id']}" and entity.frame_id == "skin"
    assert disk.pose.position.x == pytest.approx(published["x"], abs=3e-4)
    assert disk.pose.position.y == pytest.approx(published["y"], abs=3e-4)
    assert disk.size.x == pytest.approx(published["diameter"], abs=2e-4) and disk.size.x == disk.size.y
    label = re.fullmatch(r"#(\d+) ([\d.]+) N ⌀([\d.]+) mm", entity.texts[0].text)
    assert label, entity.texts[0].text
    assert int(label[1]) == published["id"] and float(label[2]) == pytest.approx(published["force"], abs=0.03)
    assert float(label[3]) == pytest.approx(published["diameter"] * 1e3, abs=0.2)
    assert [round(disk.color.r * 255), round(disk.color.g * 255), round(disk.color.b * 255)] == pytest.approx(
        list(level_rgb(published["force"] / 5.0)), abs=3)
    by_bridge = {e["bridge"]: e for e in elements["elements"]}
    assert by_bridge[5]["force"] == pytest.approx(forces[5], abs=0.03) and by_bridge[5]["touched"] is True
    assert health["links"]["gw"]["connected"] is True and "view" in health


# ---- views never slow the daemon, and leave nothing behind ----------------------------------

def _port_free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
            return True
        except OSError:
            return False


@pytest.mark.parametrize("kind", ["web", "foxglove"])
def test_a_killed_view_leaves_nothing_behind(live: Any, kind: str) -> None:
    ep, feeder, pub, _ = live
    port = free_port()
    with view_process([kind, "--port", str(port), *view_args(ep)], stdout=subprocess.PIPE) as view:
        wait_line(view)
        with socket.create_connection(("127.0.0.1", port), timeout=5):
            pass
        os.kill(view.pid, signal.SIGKILL)
        assert view.wait(10) == -signal.SIGKILL
        left = subprocess.run(["pgrep", "-s", str(view.pid)], capture_output=True, text=True).stdout
        assert left == "", f"processes left in the view's session: {left}"
        assert _port_free(port)
    seq0 = pub.client.wait_for("health")["seq"]
    assert pub.client.wait_for("health")["seq"] > seq0  # the daemon goes on


def _wmem_max() -> int:
    return int(Path("/proc/sys/net/ipv4/tcp_wmem").read_text().split()[2])


def test_a_view_that_stops_reading_loses_its_own_messages_and_counts_them(tmp_path: Path) -> None:
    """SIGSTOP a web view under a 16×16 skin at 100 Hz: the daemon goes on publishing to
    everyone else without a gap, and the view, once resumed, shows how many it lost."""
    import msgpack
    from websockets.sync.client import connect

    from cellbridge.views.source import RCVBUF, RCVHWM

    # The daemon's queue per subscriber (hwm) is what the test's own client, on a loaded
    # machine, lives on while its process waits for a core: 20 messages (0.2 s of this skin)
    # lost some of the client's own under four CPU burners. 200 gives it 2 s; the stopped
    # view loses once more was published than every queue on its way holds.
    hwm = 200
    with fed_skin(tmp_path, rows=16, cols=16) as (pty, feeder):
        cfg, ep = skin_config(tmp_path, pty, pub={"hwm": hwm})
        client = Client(ep, (b"element", b"health"))
        argv, url = start_web(ep)
        try:
            with daemon(cfg, tmp_path / "daemon.log"), view_process(argv, stdout=subprocess.PIPE) as web:
                wait_line(web)
                wait_ready(client, timeout=60)
                os.kill(web.pid, signal.SIGSTOP)
                try:
                    # stopped until more was published than every queue on the way can hold:
                    # the view's (RCVHWM messages, RCVBUF), the daemon's (hwm), the sender's kernel buffer
                    seqs, sizes = [], []
                    end = time.monotonic() + 120
                    while time.monotonic() < end:
                        got = client.sub.recv_multipart() if client.sub.poll(500) else None
                        if got is not None and got[0] == b"element":
                            seqs.append(msgpack.unpackb(got[1])["seq"])
                            sizes.append(len(got[1]))
                            bound = max(sizes) * (RCVHWM + hwm) + 2 * RCVBUF + _wmem_max() + (2 << 20)
                            if sum(sizes) > bound:
                                break
                finally:
                    os.kill(web.pid, signal.SIGCONT)
                assert len(seqs) > 100 and seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # the others lost nothing
                with connect(url.replace("http", "ws") + "ws", open_timeout=10) as ws:
                    end = time.monotonic() + 20
                    while True:
                        frame = json.loads(ws.recv(timeout=10))
                        lost = frame["counters"]["lost"].get("element", 0)
                        if lost > 0 or time.monotonic() > end:
                            break
                assert lost > 0, frame["counters"]
                assert any(f"lost {sum(frame['counters']['lost'].values())}" in s for s in frame["status"])
        finally:
            client.close()


def test_views_speak_curve_to_a_daemon_that_requires_it(tmp_path: Path) -> None:
    """With the daemon's CURVE keys a view gets the stream (its health says so); with a key
    the daemon does not allow it gets nothing, and the daemon counts the refusal."""
    from cellbridge.daemon.shell.keys import write_keypair

    from cellbridge.views.foxglove import TOPICS
    from foxglove_client import FoxgloveClient

    (tmp_path / "clients").mkdir()
    (tmp_path / "other").mkdir()
    server_pub, server_secret = write_keypair(tmp_path, "server")
    write_keypair(tmp_path / "clients", "arm")
    write_keypair(tmp_path / "other", "stranger")
    with fed_skin(tmp_path) as (pty, feeder):
        cfg, ep = skin_config(tmp_path, pty, security={"server_secret_file": server_secret,
                                                       "allowed_clients_dir": tmp_path / "clients"})
        ports = {who: free_port() for who in ("arm", "stranger")}
        secrets = {"arm": tmp_path / "clients" / "arm.key_secret", "stranger": tmp_path / "other" / "stranger.key_secret"}
        with daemon(cfg, tmp_path / "daemon.log"), \
                view_process(["foxglove", "--port", str(ports["arm"]), *view_args(ep), "--server-key", str(server_pub),
                              "--client-key", str(secrets["arm"])], stdout=subprocess.PIPE) as arm, \
                view_process(["foxglove", "--port", str(ports["stranger"]), *view_args(ep), "--server-key",
                              str(server_pub), "--client-key", str(secrets["stranger"])], stdout=subprocess.PIPE) as other:
            wait_line(arm)
            wait_line(other)
            clients = {who: FoxgloveClient(f"ws://127.0.0.1:{port}") for who, port in ports.items()}
            try:
                for c in clients.values():
                    c.wait_channels([TOPICS["health"], TOPICS["elements"]])
                    c.subscribe(TOPICS["health"])
                    c.subscribe(TOPICS["elements"])
                _, health = clients["arm"].next_message(
                    TOPICS["health"], timeout=60, pred=lambda h: h.get("security", {}).get("handshakes_denied", 0) >= 1)
                _, elements = clients["arm"].next_message(TOPICS["elements"], pred=lambda m: len(m["elements"]) == 9)
                _, nothing = clients["stranger"].next_message(TOPICS["elements"])
            finally:
                for c in clients.values():
                    c.close()
    assert health["security"]["handshakes_accepted"] >= 2  # the allowed view's SUB and control sockets
    assert nothing == {"elements": []}  # refused at the handshake: not one reading
