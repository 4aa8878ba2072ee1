"""Clients of the views for the tests: a view server started and stopped, a WebSocket client of
``cellbridge web`` reading frames as the page does, the control sequences ``cellbridge watch``
may write, and the pictures a test may keep (``CELLBRIDGE_PICTURES``)."""

from __future__ import annotations

import io
import json
import os
import re
import signal
import subprocess
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

from daemon_harness import CLI, free_port
from fake_daemon import FakeDaemon
from pty_terminal import escape_sequences

PICTURES = os.environ.get("CELLBRIDGE_PICTURES")


def args(fd: FakeDaemon) -> list[str]:
    return ["--endpoint", fd.endpoints["pub"], "--control", fd.endpoints["control"]]


@contextmanager
def server_view(kind: str, fd: FakeDaemon, *extra: str) -> Iterator[tuple[subprocess.Popen[bytes], int]]:
    """``cellbridge web`` or ``foxglove`` on a free port, up (its URL printed); always stopped."""
    port = free_port()
    proc = subprocess.Popen([CLI, kind, "--port", str(port), *args(fd), *extra], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, start_new_session=True)
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline().decode()
        assert f":{port}" in line, (line, proc.stderr.read().decode() if proc.poll() is not None else "")  # type: ignore[union-attr]
        yield proc, port
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)
        for f in (proc.stdout, proc.stderr):
            if f is not None:
                f.close()


class WebPage:
    """A WebSocket client of ``cellbridge web`` reading its frames, as the page does."""

    def __init__(self, port: int, origin: str | None = None) -> None:
        from websockets.sync.client import connect

        self._stack = ExitStack()
        self.ws = self._stack.enter_context(connect(f"ws://127.0.0.1:{port}/ws", origin=origin,  # type: ignore[arg-type]
                                                    open_timeout=10, max_size=1 << 26))
        self.frames = 0

    def frame(self, pred: Any = lambda f: True, timeout: float = 20.0) -> dict[str, Any]:
        end = time.monotonic() + timeout
        last = None
        while time.monotonic() < end:
            last = json.loads(self.ws.recv(timeout=max(0.01, end - time.monotonic())))
            self.frames += 1
            if pred(last):
                return last
        raise AssertionError(f"no matching frame within {timeout} s; last: {str(last)[:2000]}")

    def latest(self) -> dict[str, Any]:
        """The newest frame: the next one, or the last of those already waiting."""
        last = self.frame()
        while True:
            try:
                last = json.loads(self.ws.recv(timeout=0))
            except TimeoutError:
                return last
            self.frames += 1

    def close(self) -> None:
        self._stack.close()


def cell(frame: dict[str, Any], bridge: int) -> dict[str, Any] | None:
    return next((c for c in frame["cells"] if c["bridge"] == bridge), None)


def _allowed(seq: str) -> bool:
    """Whether a control sequence is one ``cellbridge watch`` (Textual) writes itself: SGR
    with truecolor colours and attributes, cursor position, private modes and their
    queries, the kitty keyboard protocol, the pointer shape (OSC 22), CR/LF/TAB."""
    if re.fullmatch(r"\x1b\[\d*;?\d*H|\x1b\[\?[\d;]+[hl]|\x1b\[\?\d+\$p|\x1b\[[<>]\d*u|\x1b\]22;[a-z-]+\x07", seq):
        return True
    m = re.fullmatch(r"\x1b\[([\d;]*)m", seq)
    if not m:
        return False
    params = [int(p) if p else 0 for p in m.group(1).split(";")]
    i = 0
    while i < len(params):
        if params[i] in (38, 48):  # truecolor only: 38;2;r;g;b
            if params[i + 1: i + 2] != [2] or len(params) < i + 5:
                return False
            i += 5
            continue
        if params[i] not in {0, 1, 2, 3, 4, 7, 8, 9, 21, 22, 23, 24, 27, 28, 29, 39, 49, 53, 55}:
            return False
        i += 1
    return True


def foreign_sequences(text: str) -> list[str]:
    return [s for s in escape_sequences(text) if not _allowed(s)]


def picture(name: str, data: bytes) -> None:
    if PICTURES:
        Path(PICTURES).mkdir(parents=True, exist_ok=True)
        (Path(PICTURES) / name).write_bytes(data)


def pixel(png: bytes, x: float, y: float) -> tuple[int, int, int]:
    from PIL import Image

    img = Image.open(io.BytesIO(png)).convert("RGB")
    return img.getpixel((int(x), int(y)))  # type: ignore[return-value]  # an RGB image: a pixel is a 3-tuple
