"""The daemon's operations hooks: systemd notification and endpoint security.

The service calls these at fixed points of its life (binding, readiness, a status line
every few seconds, the watchdog from its event loop, reload, stop). Keeping them in one
object lets the sans-I/O pipeline and the asyncio shell stay free of systemd and CURVE.
"""

from __future__ import annotations

from collections.abc import Mapping

import zmq
from cellbridge.daemon.core.config import Config
from cellbridge.daemon.ops.notify import Notifier
from cellbridge.daemon.ops.peers import PeerGuard, PeerLimits, bound_socket
from cellbridge.daemon.ops.security import CurveKeys, CurveServer, check_bind, load_curve, restrict_ipc


def curve_keys(config: Config) -> CurveKeys | None:
    """The config's CURVE keys, or None; a bad ``[security]`` table is a ValueError naming the key."""
    return load_curve(config.security, source=config.source, base_dir=config.base_dir)


class OpsHooks:
    """sd_notify (a no-op without ``NOTIFY_SOCKET``), loopback-or-CURVE binding, and the
    bounds on what peers may hold (:mod:`cellbridge.daemon.ops.peers`)."""

    def __init__(self, config: Config, env: Mapping[str, str] | None = None) -> None:
        self.config = config
        self.curve = curve_keys(config)
        self.notifier = Notifier(env)
        self.watchdog_interval = self.notifier.watchdog_interval
        self._server: CurveServer | None = None
        self._guard: PeerGuard | None = None

    def secure(self, ctx: zmq.Context, socket: zmq.Socket, endpoint: str) -> None:
        """Before binding: refuse a non-loopback endpoint without keys; with keys, a CURVE
        server; in any case bound what one peer and all of them may hold."""
        check_bind(endpoint, self.curve)
        # The ZAP handler and the peer guard run on threads with blocking sockets: give
        # them a plain context that shares the asyncio context's libzmq context (ZAP and
        # inproc:// monitors are per context).
        plain: zmq.Context[zmq.Socket[bytes]] = zmq.Context.shadow(ctx.underlying)
        role = "pub" if socket.type in (zmq.XPUB, zmq.PUB) else "control"
        peers = self.config.peers
        bound_socket(socket, role, peers, self.config.control)
        if self._guard is None:
            self._guard = PeerGuard(plain)
        self._guard.watch(role, socket, PeerLimits(peers.max_pub if role == "pub" else peers.max_control, peers.max_per_address))
        if self.curve is None:
            return
        if self._server is None:
            self._server = CurveServer(plain, self.curve)
        self._server.apply(socket)

    def bound(self, socket: zmq.Socket, endpoint: str) -> None:
        """After binding: an ipc:// socket file gets its section's ``ipc_mode`` and ``ipc_group``."""
        section = self.config.pub if socket.type in (zmq.XPUB, zmq.PUB) else self.config.control
        restrict_ipc(endpoint, section.ipc_mode, section.ipc_group)

    def counters(self) -> dict[str, object]:
        out: dict[str, object] = dict(self._server.counters()) if self._server is not None else {}
        if self._guard is not None:
            out["peers"] = self._guard.stats()
        return out

    def reload_keys(self) -> None:
        """SIGHUP: read the allowed clients' keys again (a bad directory keeps the old keys)."""
        if self._server is not None:
            self._server.reload()

    def ready(self, status: str) -> None:
        self.notifier.ready(status)

    def status(self, text: str) -> None:
        self.notifier.status(text)

    def watchdog(self) -> None:
        self.notifier.watchdog()

    def reloading(self) -> None:
        self.notifier.reloading()

    def stopping(self) -> None:
        self.notifier.stopping()

    def close(self) -> None:
        if self._guard is not None:
            self._guard.stop()
            self._guard = None
        if self._server is not None:
            self._server.stop()
            self._server = None
        self.notifier.close()
