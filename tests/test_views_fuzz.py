"""The three views fed 10 000 random and mistyped daemon messages (tests/support/view_fuzz.py), as
real processes: none exits, the web page keeps receiving (and drawing) frames afterwards
and shows what comes after, Foxglove keeps publishing, and ``cellbridge watch`` writes no
control sequence it did not make itself (none of the messages' escape sequences, raw).

The stand-in daemon's PUB queues up to a million messages per subscriber, so no view
loses one to its own slowness: the web view must have read every one of them (its
counters say so exactly). ``CELLBRIDGE_FUZZ_SEED`` picks another seed.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import pytest

from daemon_harness import CLI
from fake_daemon import FakeDaemon, grid_layout
from pty_terminal import pty_program
from support.view_clients import WebPage, args, cell, foreign_sequences, server_view
from support.view_fuzz import SOURCE, messages, odd_value, topology

N = 10_000
SEED = int(os.environ.get("CELLBRIDGE_FUZZ_SEED", "30"))


def fuzzy_reply(seed: int) -> Any:
    """Control replies: the layout, or (one in three) a mistyped one."""
    rng = random.Random(seed)
    lock = threading.Lock()

    def reply(req: Any) -> Any:
        rid = req.get("id") if isinstance(req, dict) else None
        with lock:
            r = rng.random()
            if r < 0.2:
                return dict(topology(rng, 0), id=rid, ok=True)
            if r < 0.33:
                return {"id": rid, "ok": odd_value(rng), "layout": odd_value(rng), "error": odd_value(rng)}
        return {"v": 1, "id": rid, "ok": True, "layout": grid_layout()}
    return reply


class FoxgloveReader(threading.Thread):
    """A Foxglove client subscribed to every channel, reading all the time (as the app does)."""

    def __init__(self, port: int) -> None:
        from cellbridge.views.foxglove import TOPICS
        from foxglove_client import FoxgloveClient

        super().__init__(daemon=True)
        self.client = FoxgloveClient(f"ws://127.0.0.1:{port}")
        self.client.wait_channels(list(TOPICS.values()))
        self.topic = {self.client.subscribe(t): t for t in TOPICS.values()}
        self.decoders = {t: self.client.decoder(self.client.by_topic(t)) for t in TOPICS.values()}  # type: ignore[arg-type]
        self.counts: Counter[str] = Counter()
        self.last: dict[str, Any] = {}
        self.error: BaseException | None = None
        self.stop = threading.Event()

    def run(self) -> None:
        import struct

        try:
            while not self.stop.is_set():
                try:
                    msg = self.client.ws.recv(timeout=0.5)
                except TimeoutError:
                    continue
                if isinstance(msg, str) or msg[0] != 1:
                    continue
                sid = struct.unpack_from("<I", msg, 1)[0]
                topic = self.topic.get(sid)
                if topic is not None:
                    self.counts[topic] += 1
                    self.last[topic] = self.decoders[topic](msg[13:])
        except BaseException as exc:  # the test reports it
            self.error = exc

    def close(self) -> None:
        self.stop.set()
        self.join(5)
        self.client.close()


class WebReader(threading.Thread):
    """A WebSocket client of ``cellbridge web`` reading every frame as it comes (as a page
    does: one that stops reading misses the server's heartbeat and is dropped), keeping the newest."""

    def __init__(self, port: int) -> None:
        super().__init__(daemon=True)
        self.page = WebPage(port)
        self.newest: dict[str, Any] | None = None
        self.count = 0
        self.error: BaseException | None = None
        self.stop = threading.Event()
        self.cond = threading.Condition()

    def run(self) -> None:
        try:
            while not self.stop.is_set():
                try:
                    text = self.page.ws.recv(timeout=0.5)
                except TimeoutError:
                    continue
                frame = json.loads(text)
                with self.cond:
                    self.newest, self.count = frame, self.count + 1
                    self.cond.notify_all()
        except BaseException as exc:  # the test reports it
            self.error = exc

    def frame(self, pred: Any = lambda f: True, timeout: float = 20.0) -> dict[str, Any]:
        """The next frame (after this call) that satisfies ``pred``."""
        end = time.monotonic() + timeout
        with self.cond:
            seen = self.count
            while True:
                if self.count > seen and self.newest is not None and pred(self.newest):
                    return self.newest
                seen = self.count
                left = end - time.monotonic()
                assert left > 0 and self.error is None, f"no matching frame within {timeout} s ({self.error!r}): " \
                                                        f"{str(self.newest)[:1500]}"
                self.cond.wait(min(left, 0.5))

    latest = frame

    def send(self, body: dict[str, Any]) -> None:
        self.page.ws.send(json.dumps(body))

    def close(self) -> None:
        self.stop.set()
        self.join(5)
        self.page.close()


def final_state(fd: FakeDaemon, seq: int) -> None:
    """A well-formed skin after the storm: bridge 1 at 3.5 N, uptime 4242 s."""
    fd.publish("topology", {"v": 1, "seq": seq, "source": SOURCE, "layout": grid_layout()})
    fd.publish("element", {"v": 1, "seq": seq, "source": SOURCE, "bridge": [1, 2], "force": [3.5, 0.0],
                           "valid": [True, True], "touched": [True, False], "status": [0, 2], "t_sample": [1e6, 1e6]})
    fd.publish("health", {"v": 1, "seq": seq, "source": SOURCE, "uptime": 4242.0, "links": {"gw": {"connected": True}}})


@pytest.mark.skipif(shutil.which("chromium") is None, reason="Debian's chromium is not installed (make test installs it)")
def test_the_views_survive_10000_random_and_mistyped_messages(tmp_path: Path) -> None:
    from browser import browser

    with FakeDaemon(reply=fuzzy_reply(SEED), sndhwm=1_000_000) as fd, \
            server_view("web", fd) as (web, wport), server_view("foxglove", fd) as (fx, fport), \
            pty_program([CLI, "watch", *args(fd)], cols=80, rows=24) as watch, browser(tmp_path) as page:
        page.navigate(f"http://127.0.0.1:{wport}/")
        page.wait_for("window.cellbridge && cellbridge.connects === 1", what="the page's connection")
        page.evaluate("window.__errors = []; window.addEventListener('error', (e) => __errors.push(String(e.message)))")
        client = WebReader(wport)
        client.start()
        fox = FoxgloveReader(fport)
        fox.start()
        try:
            # every view hears the stream before the storm (a SUB joins a moment after it connects)
            end = time.monotonic() + 60
            seq = 0
            while time.monotonic() < end:
                final_state(fd, seq)
                seq += 1
                time.sleep(0.1)
                try:
                    watch.wait_for(r"uptime 4242 s", timeout=0.1)
                except AssertionError:
                    continue
                if fox.counts["/cellbridge/health"] and page.evaluate("cellbridge.frame && cellbridge.frame.live"):
                    break
            client.send({"select": 1})  # the page's plot of an element: the series path too
            page.evaluate("cellbridge.select = 3, cellbridge.ws.send(JSON.stringify({select: 3}))")
            before = client.latest()["counters"]
            while True:  # nothing of the warm-up left in flight: the counts hold still
                time.sleep(0.5)
                now = client.latest()["counters"]
                if now["received"] == before["received"]:
                    break
                before = now
            mark = len(watch.output)
            page_frames = page.evaluate("cellbridge.frames")

            expected: Counter[str] = Counter()
            for i, msg in enumerate(messages(SEED, N)):
                fd.publish_raw(msg.frames)
                if msg.topic is not None:
                    expected[msg.topic] += 1
                if i % 500 == 0:
                    assert web.poll() is None and fx.poll() is None and watch.proc.poll() is None, f"a view exited at {i}"

            # the web view read every message (nothing lost: the PUB queues them), and goes on
            want = {t: before["received"].get(t, 0) + n for t, n in expected.items()}
            f = client.frame(lambda f: all(f["counters"]["received"].get(t, 0) >= n for t, n in want.items()),
                             timeout=300)
            assert {t: f["counters"]["received"].get(t, 0) for t in want} == want
            assert f["counters"]["malformed"] > before["malformed"] and f["counters"]["other_sources"] > 0
            # and shows what comes after the storm, as do the other two
            end = time.monotonic() + 120
            while time.monotonic() < end:
                final_state(fd, seq)
                seq += 1
                f = client.frame(timeout=30)
                if (cell(f, 1) or {}).get("force") == 3.5 and f["live"]:
                    break
            assert (cell(f, 1) or {}).get("force") == 3.5, f["status"]
            assert any("uptime 4242 s" in s for s in f["status"])
            page.wait_for("cellbridge.frame.cells.some((c) => c.bridge === 1 && c.force === 3.5) && "
                          f"cellbridge.frames > {page_frames} + 10", timeout=60, what="frames after the storm")
            assert page.evaluate("window.__errors") == []
            elements = fox.last.get("/cellbridge/elements", {}).get("elements", [])
            end = time.monotonic() + 60
            while not any(e["bridge"] == 1 and e["force"] == 3.5 for e in elements) and time.monotonic() < end:
                final_state(fd, seq)
                seq += 1
                time.sleep(0.2)
                elements = fox.last.get("/cellbridge/elements", {}).get("elements", [])
            assert any(e["bridge"] == 1 and e["force"] == 3.5 for e in elements)
            assert fox.error is None, fox.error
            end = time.monotonic() + 30
            while fox.last["/cellbridge/health"].get("uptime") != 4242.0 and time.monotonic() < end:
                final_state(fd, seq)
                seq += 1
                time.sleep(0.2)
            assert fox.last["/cellbridge/health"]["view"]["errors"] == 0  # its last-resort guard never caught anything
            end = time.monotonic() + 120
            while time.monotonic() < end:  # the terminal is the slowest of the three: it may still be reading
                final_state(fd, seq)
                seq += 1
                try:
                    watch.wait_for(r"uptime 4242 s", since=mark, timeout=0.3)
                    break
                except AssertionError:
                    continue
            watch.wait_for(r"uptime 4242 s", since=mark, timeout=1)
            assert web.poll() is None and fx.poll() is None and watch.proc.poll() is None
        finally:
            fox.close()
            client.close()
        out = bytes(watch.output[mark:]).decode("utf-8", "replace")
        assert foreign_sequences(out) == [], sorted(set(foreign_sequences(out)))[:20]
        assert "\x1b]52" not in out and "\x1b[31m" not in out and "view errors" not in out
        assert f["view"]["errors"] == 0  # the page server's last-resort guard never had to catch anything
