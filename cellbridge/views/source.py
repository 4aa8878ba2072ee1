"""The views' thin ZeroMQ shell: a SUB socket on the daemon's PUB, a DEALER on its control.

Every view is a subscriber like any other (``docs/zmq-api.md``): it never slows the
daemon. Its receive queue is bounded (``RCVHWM``, ``RCVBUF``); a view that falls behind loses
messages inside ZeroMQ, sees them as gaps in ``seq`` and shows the count
(:attr:`SkinView.lost`). ZeroMQ reconnects by itself when the daemon restarts; the
model notices the restart (sequence numbers start again) and asks for the layout anew.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import msgpack
import zmq

from cellbridge.daemon.ops.security import apply_client
from cellbridge.views.model import TOPICS, SkinView, printable

DEFAULT_PUB = "tcp://127.0.0.1:5560"
DEFAULT_CONTROL = "tcp://127.0.0.1:5561"
# A view draws the newest state: a backlog would only show the past late. So at most
# RCVHWM messages wait inside ZeroMQ and RCVBUF bytes in the kernel (about a second of a
# 16×16 skin at 100 Hz); beyond that the view loses messages, and counts them.
RCVHWM = 200
RCVBUF = 1 << 20
TOPOLOGY_RETRY = 1.0  # s between layout requests while the layout is unknown
TARE_ANSWER_S = 3.0  # s a tare waits for the daemon's answer before the view says none came


def add_source_arguments(parser: argparse.ArgumentParser) -> None:
    """The options every view shares: where the daemon is, which one, its CURVE keys, colour scale."""
    g = parser.add_argument_group("daemon")
    g.add_argument("--endpoint", default=DEFAULT_PUB, help=f"the daemon's PUB endpoint (default: {DEFAULT_PUB})")
    g.add_argument("--source", metavar="NAME",
                   help="show only the daemon whose messages name this source (several daemons behind one "
                        "'cellbridge proxy'; a daemon's source is its [pub] source, by default HOST:PORT of its "
                        "PUB endpoint); default: the first daemon heard, others are counted, never mixed in. "
                        "--control must then be that daemon's control endpoint")
    g.add_argument("--control", default=DEFAULT_CONTROL,
                   help=f"the daemon's control endpoint, for the layout and tare (default: {DEFAULT_CONTROL})")
    g.add_argument("--server-key", type=Path, metavar="FILE",
                   help="the daemon's public key file (NAME.key) when it runs with CURVE")
    g.add_argument("--client-key", type=Path, metavar="FILE",
                   help="this client's secret key file (NAME.key_secret); its NAME.key must be allowed")
    g.add_argument("--force-scale", type=float, default=5.0, metavar="N",
                   help="force drawn at full colour, newtons (default: 5)")


def check_source_arguments(args: argparse.Namespace) -> str | None:
    """A sentence saying what is wrong with the shared options, or None."""
    if (args.server_key is None) != (args.client_key is None):
        return "--server-key and --client-key go together (CURVE needs both)"
    if not args.force_scale > 0:
        return f"--force-scale must be > 0, got {args.force_scale}"
    return None


def open_source(command: str, args: argparse.Namespace, problem: str | None) -> Source | None:
    """The view's :class:`Source`, or None after saying on stderr why not: ``problem``
    (the view's own option checks), a bad shared option, or a bad key file."""
    problem = check_source_arguments(args) or problem
    if problem is None:
        try:
            return Source(args.endpoint, args.control, args.server_key, args.client_key)
        except (ValueError, OSError) as exc:
            problem = str(exc)
    print(f"cellbridge {command}: {problem}", file=sys.stderr)
    return None


def _feed(model: SkinView, parts: list[bytes], now: float) -> None:
    if len(parts) != 2:
        model.feed_malformed(now)
        return
    try:
        payload = msgpack.unpackb(parts[1], raw=False, strict_map_key=False)
    except Exception:  # not msgpack, too deep, a map keyed by an array (TypeError): counted
        model.feed_malformed(now)
        return
    model.feed(parts[0].decode("ascii", "replace"), payload, now)


class Source:
    """The daemon's stream, drained into a :class:`SkinView` without blocking."""

    def __init__(self, endpoint: str, control: str, server_key: Path | None = None,
                 client_key: Path | None = None, topics: tuple[str, ...] = TOPICS, rcvhwm: int = RCVHWM) -> None:
        self.context = zmq.Context()
        self.sub = self.context.socket(zmq.SUB)
        self.ctl = self.context.socket(zmq.DEALER)
        # a request is sent to a daemon connected now, or not at all: a tare queued for a
        # control socket nobody serves (a replay's) would re-baseline a daemon started later
        self.ctl.immediate = True
        self.control = control
        for s in (self.sub, self.ctl):
            s.linger = 0
            if server_key is not None and client_key is not None:
                apply_client(s, server_key, client_key)
        self.sub.rcvhwm = rcvhwm  # a recorder (cellbridge record --profile ros2) keeps a deeper queue
        self.sub.rcvbuf = RCVBUF
        for t in topics:
            self.sub.subscribe(t)
        for option, sock, address in (("--endpoint", self.sub, endpoint), ("--control", self.ctl, control)):
            try:
                sock.connect(address)
            except zmq.ZMQError as exc:  # '127.0.0.1:5560' (no tcp://), a port missing: said, not a traceback
                self.close()
                reason = zmq.strerror(exc.errno) if exc.errno is not None else str(exc)
                raise ValueError(f"{option} {address}: {reason}: not an endpoint to connect to "
                                 "(tcp://HOST:PORT or ipc://PATH)") from None
        self.poller = zmq.Poller()
        self.poller.register(self.sub, zmq.POLLIN)
        self.poller.register(self.ctl, zmq.POLLIN)
        self._next_id = 0
        self._pending: dict[int, tuple[str, float]] = {}  # request id: its command, when it was sent
        self._topology_at = -1e9
        self.notice = ""  # the last control reply worth showing ("tare: 16 elements")

    def poll(self, timeout_ms: int) -> bool:
        """Whether something is waiting (blocks up to ``timeout_ms``)."""
        return bool(self.poller.poll(timeout_ms))

    def drain(self, model: SkinView, max_messages: int = 100_000) -> int:
        """Feed every waiting message to ``model``; returns how many. Also asks for the
        layout when the model needs it and handles control replies."""
        n = 0
        now = time.monotonic()
        while n < max_messages:
            try:
                parts = self.sub.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                break
            n += 1
            _feed(model, parts, now)
        self._answer(model, now)
        return n

    def feed_received(self, model: SkinView, received: list[list[bytes]]) -> int:
        """As :meth:`drain`, of messages another thread took off :attr:`sub` (which is then
        that thread's alone: the caller never polls or drains this source)."""
        now = time.monotonic()
        for parts in received:
            _feed(model, parts, now)
        self._answer(model, now)
        return len(received)

    def _answer(self, model: SkinView, now: float) -> None:
        self._replies(model)
        self._unanswered(now)
        if model.needs_topology and now - self._topology_at >= TOPOLOGY_RETRY:
            # not sent (not connected yet, or a replay): asked again soon, not a second later
            self._topology_at = now if self.request({"v": 1, "cmd": "topology"}) else now - TOPOLOGY_RETRY + 0.1

    def request(self, body: dict[str, Any]) -> bool:
        """Send a control request; its reply is taken in a later :meth:`drain`. False when
        no daemon's control socket is connected to take it (nothing is sent)."""
        self._next_id += 1
        body = dict(body, id=self._next_id)
        try:
            self.ctl.send(msgpack.packb(body), zmq.NOBLOCK)
        except zmq.Again:
            return False
        self._pending[self._next_id] = (str(body.get("cmd")), time.monotonic())
        if len(self._pending) > 16:  # a daemon that never answers: forget the oldest
            self._pending.pop(next(iter(self._pending)))
        return True

    def tare(self) -> None:
        """Ask the daemon to tare; :attr:`notice` says what became of it: sent, then its
        answer, or that none came (a replay, or a proxy, has no control socket)."""
        self.notice = ("tare: sent" if self.request({"v": 1, "cmd": "tare"}) else
                       f"tare: not sent: no daemon answers on {self.control} (a replay has no control socket)")

    def _unanswered(self, now: float) -> None:
        for rid, (cmd, sent) in list(self._pending.items()):
            if cmd == "tare" and now - sent > TARE_ANSWER_S:
                del self._pending[rid]
                self.notice = (f"tare: no answer from {self.control} in {TARE_ANSWER_S:g} s "
                               "(the daemon may not have tared)")

    def _replies(self, model: SkinView) -> None:
        while True:
            try:
                frames = self.ctl.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            try:
                reply = msgpack.unpackb(frames[-1], raw=False, strict_map_key=False)
            except Exception:  # as in drain()
                model.feed_malformed(time.monotonic())
                continue
            if not isinstance(reply, dict):
                continue
            rid = reply.get("id")
            cmd, _ = self._pending.pop(rid, (None, 0.0)) if isinstance(rid, int) else (None, 0.0)
            if cmd == "topology" and reply.get("ok") is True:
                model.feed_topology(reply)
            elif cmd == "tare":
                n = reply.get("tared_elements")
                self.notice = (f"tare: {n if isinstance(n, int) else '?'} elements re-baselining"
                               if reply.get("ok") is True else f"tare refused: {printable(reply.get('error'), 80)}")
                model.changed = True

    def close(self) -> None:
        self.context.destroy(linger=0)
