"""The daemon's operations hooks: systemd notification and endpoint security.

The service calls these at fixed points of its life (binding, readiness, a status line
every few seconds, the watchdog from its event loop, reload, stop). Keeping them in one
object lets the sans-I/O pipeline and the asyncio shell stay free of systemd and CURVE.
"""

from __future__ import annotations

from collections.abc import Mapping

import zmq

from cellbridge.daemon.config import Config
from cellbridge.daemon.notify import Notifier
from cellbridge.daemon.security import CurveKeys, CurveServer, check_bind, load_curve


def curve_keys(config: Config) -> CurveKeys | None:
    """The config's CURVE keys, or None; a bad ``[security]`` table is a ValueError naming the key."""
    return load_curve(config.security, source=config.source, base_dir=config.base_dir)


class OpsHooks:
    """sd_notify (a no-op without ``NOTIFY_SOCKET``) and loopback-or-CURVE binding."""

    def __init__(self, config: Config, env: Mapping[str, str] | None = None) -> None:
        self.curve = curve_keys(config)
        self.notifier = Notifier(env)
        self.watchdog_interval = self.notifier.watchdog_interval
        self._server: CurveServer | None = None

    def secure(self, ctx: zmq.Context, socket: zmq.Socket, endpoint: str) -> None:
        """Before binding: refuse a non-loopback endpoint without keys; with keys, a CURVE server."""
        check_bind(endpoint, self.curve)
        if self.curve is None:
            return
        if self._server is None:
            # The ZAP handler runs on a thread with blocking sockets: give it a plain
            # context that shares the asyncio context's libzmq context (ZAP is per context).
            self._server = CurveServer(zmq.Context.shadow(ctx.underlying), self.curve)
        self._server.apply(socket)

    def counters(self) -> dict[str, int]:
        return self._server.counters() if self._server is not None else {}

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
        if self._server is not None:
            self._server.stop()
            self._server = None
        self.notifier.close()
