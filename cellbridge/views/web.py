"""``cellbridge web``: the skin on one web page, served on loopback, live over a WebSocket.

The page (``static/``: HTML, JavaScript and CSS shipped in the package: no CDN, no build
step) draws what :class:`~cellbridge.views.model.SkinView` computes: the element grid by
force, each contact as a disk at its estimated position with its id, force and
diameter, the force over time of a clicked element, and the mesh's health. It
reconnects by itself, to this server and (through ZeroMQ) to a restarted daemon.

Threads: one drains the daemon's ZeroMQ stream into the model (never blocking the
daemon: a slow view loses messages in its own queue and counts them); the asyncio
loop serves HTTP and pushes a frame to every page at most ``--max-rate`` times a
second. A page that does not keep up is skipped for that frame (counted), never queued.

Every request passes :mod:`cellbridge.views.access` first: a ``Host`` the server is not
known by (DNS rebinding) and an ``Origin`` that is not the page's own (another site's
page opening the WebSocket) are answered 403. On SIGTERM, SIGHUP or Ctrl-C every page
gets a close frame (1001, going away) and the server exits within a second; a second
signal meanwhile changes nothing.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hmac
import ipaddress
import json
import math
import socket
import sys
import threading
import time
from importlib import resources
from pathlib import Path
from typing import Any

from cellbridge.views.access import host_allowed, origin_allowed
from cellbridge.views.model import Frame, SkinView, level_rgb
from cellbridge.views.signals import ignore_stop_signals, on_stop_signal
from cellbridge.views.source import Source, add_source_arguments, open_source

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080
STATIC = ("index.html", "app.js", "style.css")
CLOSE_WAIT = 0.5  #: s a page has to answer the close frame on stop (then its connection is dropped)
#: Bytes of frames the kernel holds for a page. A page that reads slowly (a slow link, a
#: busy browser) then makes the server skip frames (counted) instead of queueing seconds
#: of them, and the heartbeat's ping is not stuck behind megabytes.
PAGE_SNDBUF = 256 * 1024
HEARTBEAT = 20.0  #: s between pings to a page; one not answered within half that is closed (a dead page)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Serve one page that shows a running daemon's skin: elements coloured by force,\n"
        "contacts as disks at their estimated position (id, force, diameter), the force\n"
        "over time of a clicked element, and the mesh's health. Open the printed URL.\n"
        "A skin on a robot (a daemon whose [layout] file is a skin description) is drawn\n"
        "patch by patch, titled by link and name; each contact says where on the robot.\n\n"
        "The page is on loopback (127.0.0.1) by default, reachable from this host only.\n"
        "Binding elsewhere (--host 0.0.0.0, a LAN address) is refused unless access is\n"
        "protected by a token (--token-file): the page and its WebSocket then answer only\n"
        "to URLs carrying ?token=... . The token travels in clear over plain HTTP: on an\n"
        "untrusted network prefer loopback and an SSH tunnel (ssh -L 8080:127.0.0.1:8080).\n\n"
        "Only the page itself may open its WebSocket (another site's page is refused by its\n"
        "Origin), and only requests naming this server are answered (DNS rebinding): by an\n"
        "IP address, localhost, the --host name, this machine's host name, or a name given\n"
        "with --allow-host (e.g. robot.local when the page is opened as http://robot.local:8080/).\n\n"
        "examples:\n"
        "  cellbridge web                                  # http://127.0.0.1:8080/\n"
        "  cellbridge web --port 8090 --endpoint tcp://127.0.0.1:5560\n"
        "  cellbridge web --host 0.0.0.0 --token-file /etc/cellbridge/web.token\n"
        "  cellbridge web --endpoint tcp://127.0.0.1:5570 --source robot:5562 \\\n"
        "      --control tcp://127.0.0.1:5563          # one of two daemons behind cellbridge proxy"
    )
    add_source_arguments(parser)
    g = parser.add_argument_group("page")
    g.add_argument("--host", default=DEFAULT_HOST, help=f"address to serve on (default: {DEFAULT_HOST})")
    g.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"TCP port (default: {DEFAULT_PORT}; 0: any free port)")
    g.add_argument("--token-file", type=Path, metavar="FILE",
                   help="file holding the access token (one line); required beyond loopback")
    g.add_argument("--max-rate", type=float, default=60.0, metavar="HZ",
                   help="most frames pushed to a page a second (default: 60)")
    g.add_argument("--allow-host", action="append", default=[], metavar="NAME",
                   help="a further name this server is reached by (the Host of the page's URL); repeat for more")


def is_loopback_host(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def read_token(path: Path) -> str:
    """The access token in ``path``; ValueError with a sentence naming the file when it
    cannot be read ('[Errno 2] No such file or directory: ...' was Python's, not ours)."""
    try:
        token = path.read_text(encoding="utf-8").strip()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read the token: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: the token must be text (UTF-8)") from None
    if len(token) < 16:
        raise ValueError(f"{path}: the token must be at least 16 characters (e.g. python3 -c "
                         f"'import secrets; print(secrets.token_urlsafe())' > {path})")
    return token


def frame_json(frame: Frame) -> dict[str, Any]:
    """A frame as the page's JSON: colours computed here (one ramp for every view), NaN as null."""
    def num(v: float) -> float | None:
        return v if math.isfinite(v) else None
    return {
        "type": "frame", "rows": frame.rows, "cols": frame.cols, "side": frame.side,
        "quantity": frame.quantity, "scale": frame.scale, "live": frame.live, "paused": frame.paused,
        "cells": [{"bridge": c.bridge, "row": c.row, "col": c.col, "rgb": level_rgb(c.level), "label": c.label,
                   "touched": c.touched, "force": num(c.force)} for c in frame.cells],
        "contacts": [{"id": c.id, "col": num(c.col), "row": num(c.row), "diameter": num(c.diameter),
                      "rgb": level_rgb(c.level), "label": c.label, "line": c.line, "force": num(c.force),
                      "x": num(c.x), "y": num(c.y), "diameter_m": num(c.diameter_m),
                      "observable": list(c.observable)} for c in frame.contacts],
        "patches": [{"title": b.title, "short": b.short, "row0": b.row0, "col0": b.col0, "rows": b.rows, "cols": b.cols}
                    for b in frame.patches],
        "status": frame.status, "counters": frame.counters,
    }


class WebView:
    """The page server: shared model, ZeroMQ thread, pages and their frames."""

    def __init__(self, source: Source, model: SkinView, token: str | None, max_rate: float,
                 hosts: tuple[str, ...] = ()) -> None:
        self.source, self.model = source, model
        self.token = token
        self.hosts = hosts  # names the server answers to, beyond IP addresses and localhost
        self.period = 1.0 / max_rate
        self.lock = threading.Lock()
        self.stop = threading.Event()
        self.pages: dict[Any, dict[str, Any]] = {}  # websocket -> {"select": bridge, "sent_t": t, "busy": bool}
        self.counters = {"frames": 0, "skipped": 0, "pages": 0, "refused": 0, "errors": 0}
        self._error_said = False
        self.loop: asyncio.AbstractEventLoop | None = None
        self.wake: asyncio.Event | None = None

    # ---- ZeroMQ thread -------------------------------------------------------------

    def pump(self) -> None:
        while not self.stop.is_set():
            ready = self.source.poll(200)
            n = 0
            with self.lock:
                try:
                    n = self.source.drain(self.model) if ready else self.source.drain(self.model, 0)
                except Exception as exc:  # the model never raises on a payload; should anything else, go on
                    self._error(exc)
            if (n or not ready) and self.loop is not None and self.wake is not None:
                self.loop.call_soon_threadsafe(self.wake.set)

    def _error(self, exc: Exception) -> None:
        """Count an unforeseen error and say the first on stderr: the page must not freeze."""
        self.counters["errors"] += 1
        if not self._error_said:
            self._error_said = True
            print(f"cellbridge web: error (going on, counted in the page's view counters): "
                  f"{type(exc).__name__}: {exc}", file=sys.stderr, flush=True)

    # ---- asyncio side --------------------------------------------------------------

    def allowed(self, request: Any) -> bool:
        if self.token is None:
            return True
        given = request.query.get("token", "")
        return hmac.compare_digest(given.encode(), self.token.encode())

    def refusal(self, request: Any) -> str | None:
        """Why a request is refused by its ``Host`` or ``Origin`` (see :mod:`cellbridge.views.access`), or None."""
        host = request.headers.get("Host")
        if not host_allowed(host, self.hosts):
            return "403: this server does not answer to that host name (see cellbridge web --help, --allow-host)\n"
        if not origin_allowed(request.headers.get("Origin"), host):
            return "403: only this server's own page may connect\n"
        return None

    def guard(self) -> Any:
        """The aiohttp middleware applying :meth:`refusal` to every request."""
        from aiohttp import web

        @web.middleware
        async def middleware(request: Any, handler: Any) -> Any:
            why = self.refusal(request)
            if why is not None:
                self.counters["refused"] += 1
                return web.Response(status=403, text=why)
            return await handler(request)
        return middleware

    async def index(self, request: Any) -> Any:
        from aiohttp import web
        if not self.allowed(request):
            return web.Response(status=403, text="403: this page needs ?token=... (see cellbridge web --help)\n")
        return await self.static_file(request, "index.html")

    async def static(self, request: Any) -> Any:
        return await self.static_file(request, request.match_info["name"])

    async def static_file(self, request: Any, name: str) -> Any:
        from aiohttp import web
        if name not in STATIC:
            raise web.HTTPNotFound()
        body = resources.files("cellbridge.views").joinpath("static", name).read_bytes()
        ctype = {"html": "text/html", "js": "text/javascript", "css": "text/css"}[name.rsplit(".", 1)[1]]
        return web.Response(body=body, content_type=ctype, charset="utf-8",
                            headers={"Cache-Control": "no-cache"})

    async def websocket(self, request: Any) -> Any:
        from aiohttp import WSMsgType, web
        if not self.allowed(request):
            return web.Response(status=403, text="403: token required\n")
        ws = web.WebSocketResponse(heartbeat=HEARTBEAT, timeout=CLOSE_WAIT)
        await ws.prepare(request)
        sock = request.transport.get_extra_info("socket") if request.transport is not None else None
        if sock is not None:  # few frames wait in the kernel: a slow page gets the newest, never a backlog
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, PAGE_SNDBUF)
        self.pages[ws] = {"select": None, "sent_t": -math.inf, "busy": False}
        self.counters["pages"] += 1
        try:
            async for msg in ws:
                if msg.type != WSMsgType.TEXT:
                    continue
                try:
                    body = json.loads(msg.data)
                except ValueError:
                    continue
                if isinstance(body, dict) and "select" in body:
                    sel = body["select"]
                    self.pages[ws].update(select=sel if isinstance(sel, int) else None, sent_t=-math.inf)
                    if self.wake is not None:
                        self.wake.set()
        finally:
            self.pages.pop(ws, None)
        return ws

    async def broadcast(self) -> None:
        assert self.wake is not None
        while True:
            await self.wake.wait()
            self.wake.clear()
            now = time.monotonic()
            if self.pages:
                try:
                    self._push(now)
                except Exception as exc:  # as in pump(): a frame that cannot be made is counted, the next one tried
                    self._error(exc)
            await asyncio.sleep(max(0.0, self.period - (time.monotonic() - now)))

    def _push(self, now: float) -> None:
        with self.lock:
            frame = frame_json(self.model.frame(now))
            series = {ws: self._series(st) for ws, st in self.pages.items()}
        frame["view"] = dict(self.counters)
        for ws, st in list(self.pages.items()):
            if st["busy"]:
                self.counters["skipped"] += 1
                continue
            body = dict(frame, series=series.get(ws))
            st["busy"] = True
            asyncio.ensure_future(self._send(ws, st, json.dumps(body, allow_nan=False)))
        self.counters["frames"] += 1

    def _series(self, st: dict[str, Any]) -> dict[str, Any] | None:
        """New (t, force, ΔC1) points of the page's selected element since the last frame sent."""
        b = st["select"]
        e = self.model.elements.get(b) if b is not None else None
        if e is None:
            return None
        after = st["sent_t"]
        pts = [[t, _fin(f), _fin(d * 1e12)] for t, f, d in e.history
               if math.isfinite(t) and (t > after or not math.isfinite(after))]
        if pts:
            st["sent_t"] = pts[-1][0]
        return {"bridge": b, "points": pts, "reset": not math.isfinite(after)}

    async def _send(self, ws: Any, st: dict[str, Any], text: str) -> None:
        try:
            await ws.send_str(text)
        except (ConnectionError, RuntimeError):
            pass
        finally:
            st["busy"] = False

    async def serve(self, host: str, port: int) -> None:
        from aiohttp import web
        self.loop = asyncio.get_running_loop()
        self.wake = asyncio.Event()
        app = web.Application(middlewares=[self.guard()])
        app.router.add_get("/", self.index)
        app.router.add_get("/static/{name}", self.static)
        app.router.add_get("/ws", self.websocket)
        runner = web.AppRunner(app, access_log=None, shutdown_timeout=CLOSE_WAIT)
        await runner.setup()
        site = web.TCPSite(runner, host, port)
        await site.start()
        bound = runner.addresses[0][1] if runner.addresses else port
        query = f"?token={self.token}" if self.token else ""
        print(f"cellbridge web: http://{host if ':' not in host else f'[{host}]'}:{bound}/{query}", flush=True)
        thread = threading.Thread(target=self.pump, name="zmq", daemon=True)
        thread.start()
        stopping = asyncio.Event()
        loop = self.loop
        on_stop_signal(lambda: loop.call_soon_threadsafe(stopping.set))
        pushing = asyncio.ensure_future(self.broadcast())
        try:
            await asyncio.wait([pushing, asyncio.ensure_future(stopping.wait())],
                               return_when=asyncio.FIRST_COMPLETED)
        finally:
            ignore_stop_signals()
            pushing.cancel()
            await self.close_pages()
            self.stop.set()
            await runner.cleanup()
            thread.join(1)
        if pushing.done() and not pushing.cancelled() and pushing.exception() is not None:
            raise pushing.exception()  # type: ignore[misc]  # checked just above

    async def close_pages(self) -> None:
        """A close frame (1001, going away) to every page, waiting at most :data:`CLOSE_WAIT`
        for their answers: a page knows the server stopped (and reconnects later)."""
        from aiohttp import WSCloseCode

        closing = [asyncio.ensure_future(ws.close(code=WSCloseCode.GOING_AWAY, message=b"server stopping"))
                   for ws in list(self.pages)]
        if closing:
            await asyncio.wait(closing, timeout=CLOSE_WAIT)


def _fin(v: float) -> float | None:
    return v if math.isfinite(v) else None


def run(args: argparse.Namespace) -> int:
    problem = None
    if not 1 <= args.max_rate <= 240:
        problem = f"--max-rate must be within 1..240, got {args.max_rate}"
    if problem is None and not 0 <= args.port <= 65535:
        problem = f"--port must be within 0..65535, got {args.port}"
    token = None
    if problem is None and args.token_file is not None:
        try:
            token = read_token(args.token_file)
        except (OSError, ValueError) as exc:
            problem = str(exc)
    if problem is None and token is None and not is_loopback_host(args.host):
        problem = (f"refusing to serve on {args.host}: beyond loopback the page needs a token "
                   f"(--token-file FILE; e.g. python3 -c 'import secrets; print(secrets.token_urlsafe())' > FILE)")
    source = open_source("web", args, problem)
    if source is None:
        return 2
    hosts = (args.host, socket.gethostname(), *args.allow_host)
    view = WebView(source, SkinView(force_scale=args.force_scale, source=args.source), token, args.max_rate, hosts)
    try:
        asyncio.run(view.serve(args.host, args.port))
    except KeyboardInterrupt:
        pass
    except OSError as exc:
        print(f"cellbridge web: cannot serve on {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 1
    finally:
        view.stop.set()
        source.close()
    return 0


