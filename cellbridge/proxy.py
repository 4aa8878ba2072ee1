"""``cellbridge proxy``: several daemons as one stream, through libzmq's own proxy.

An XSUB socket connects to every daemon's PUB endpoint (``--back``), an XPUB socket is
bound for subscribers (``--front``), and ``zmq_proxy_steerable`` moves messages between
them inside libzmq (no Python per message). Subscriptions travel upstream, so a daemon
still builds only the topics someone behind the proxy reads. Every payload carries its
daemon's ``source`` (config ``pub.source``, default the host name): the one field that
tells the streams apart.

Security as the daemon does it: the front binds loopback only, unless it is a CURVE
server (``--server-secret``, ``--allowed-clients``; the same key files and the same
ZAP check, :class:`cellbridge.daemon.ops.security.CurveServer`), and a subscriber without
an allowed key gets nothing. A CURVE daemon behind the proxy is reached as any client
reaches it: its public key (``--back ENDPOINT=SERVER.key``) and the proxy's own key pair
(``--client-key``). SIGINT and SIGTERM stop the proxy cleanly (status 0); should its
proxy thread end by itself, the process ends too, with status 1 and the reason on its
last line, rather than stay up forwarding nothing (its supervisor then restarts it).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

import zmq

from cellbridge.daemon.ops.security import CurveKeys, CurveServer, apply_client, check_bind

DEFAULT_FRONT = "tcp://127.0.0.1:5570"


@dataclass(frozen=True)
class Backend:
    endpoint: str
    server_key: Path | None = None


def parse_backend(text: str) -> Backend:
    """``tcp://robot:5560`` or ``tcp://robot:5560=robot-server.key`` (a CURVE daemon). Not
    ``inproc://``: that reaches only this process, where no daemon runs (it was taken, and
    the proxy then waited for ever on a back that could never come)."""
    endpoint, sep, key = text.partition("=")
    if not endpoint.startswith(("tcp://", "ipc://")):
        raise argparse.ArgumentTypeError(f"{text!r}: a ZeroMQ endpoint (tcp://HOST:PORT or ipc://PATH), "
                                         "optionally =SERVER.key")
    return Backend(endpoint, Path(key) if sep else None)


def parse_front(text: str) -> str:
    """``--front``: an endpoint to bind, ``tcp://HOST:PORT`` or ``ipc://PATH`` (``127.0.0.1:5570``,
    tcp:// left out, was refused as "not a loopback endpoint")."""
    if not text.startswith(("tcp://", "ipc://")):
        raise argparse.ArgumentTypeError(f"{text!r}: a ZeroMQ endpoint to bind (tcp://HOST:PORT or ipc://PATH)")
    return text


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Merge several daemons' PUB streams into one (libzmq's XSUB/XPUB proxy). Subscribers\n"
        "connect to --front as to a daemon; subscriptions are passed on to every daemon; each\n"
        "payload's 'source' names the daemon it came from. Ends on SIGINT or SIGTERM (status\n"
        "0), or with status 1 should libzmq's proxy loop fail, its last line saying why.\n\n"
        "examples:\n"
        "  cellbridge proxy --back tcp://127.0.0.1:5560 --back tcp://127.0.0.1:5562\n"
        "  cellbridge proxy --front tcp://0.0.0.0:5570 --server-secret proxy.key_secret \\\n"
        "      --allowed-clients clients/ --back tcp://127.0.0.1:5560   # CURVE towards subscribers\n"
        "  cellbridge proxy --back tcp://arm:5560=arm-server.key --client-key proxy.key_secret\n"
        "                                                              # a CURVE daemon behind it"
    )
    parser.add_argument("--front", type=parse_front, default=DEFAULT_FRONT,
                        help=f"endpoint subscribers connect to (XPUB, bound; default {DEFAULT_FRONT})")
    parser.add_argument("--back", type=parse_backend, action="append", required=True, metavar="ENDPOINT[=KEY]",
                        help="a daemon's PUB endpoint (repeat for each); =SERVER.key for a CURVE daemon")
    parser.add_argument("--client-key", type=Path, metavar="FILE",
                        help="the proxy's own secret key file, for CURVE daemons behind it")
    parser.add_argument("--server-secret", type=Path, metavar="FILE",
                        help="the proxy's server secret key (NAME.key_secret): CURVE on the front")
    parser.add_argument("--allowed-clients", type=Path, metavar="DIR",
                        help="directory of allowed subscribers' public keys (*.key), with --server-secret")
    parser.add_argument("--hwm", type=int, default=10_000,
                        help="messages queued per subscriber, at least 1 (default 10000); a subscriber that falls "
                             "further behind loses messages, and sees the gaps in seq")


class Proxy:
    """The sockets and the proxy thread; :meth:`stop` ends it from any thread."""

    def __init__(self, front: str, backends: list[Backend], *, client_key: Path | None = None,
                 curve: CurveKeys | None = None, hwm: int = 10_000) -> None:
        check_bind(front, curve)
        self.ctx = zmq.Context()
        self.curve: CurveServer | None = None
        self._control_addr = f"inproc://proxy-control-{id(self)}"
        self.xpub = self.ctx.socket(zmq.XPUB)
        self.xsub = self.ctx.socket(zmq.XSUB)
        self.control = self.ctx.socket(zmq.PAIR)
        self._command = self.ctx.socket(zmq.PAIR)
        try:
            for s in (self.xpub, self.xsub, self.control, self._command):
                s.linger = 0
            self.xpub.sndhwm = hwm
            self.xsub.rcvhwm = hwm
            if curve is not None:
                self.curve = CurveServer(self.ctx, curve)
                self.curve.apply(self.xpub)
            self.xpub.bind(front)
            for b in sorted(backends, key=lambda b: b.server_key is not None):  # plain ones before CURVE
                if b.server_key is not None:
                    if client_key is None:
                        raise ValueError(f"{b.endpoint}: a CURVE daemon needs --client-key (the proxy's key pair)")
                    apply_client(self.xsub, b.server_key, client_key)  # taken at connect: per daemon
                self.xsub.connect(b.endpoint)
            self.control.bind(self._control_addr)
            self._command.connect(self._control_addr)
        except BaseException:
            self.close()
            raise
        self._thread = threading.Thread(target=self._run, name="zmq proxy", daemon=True)
        self._stopping = False
        self._error: str | None = None

    def _run(self) -> None:
        try:
            zmq.proxy_steerable(self.xpub, self.xsub, None, self.control)
        except zmq.ContextTerminated:
            pass
        except Exception as exc:  # (any: the thread ends either way, and :meth:`failure` says why)
            self._error = f"{type(exc).__name__}: {exc}"
        if not self._stopping and self._error is None:
            self._error = "the proxy loop ended by itself"

    def failure(self) -> str | None:
        """Why the proxy thread ended when nobody stopped it (None: it runs, or was stopped).
        A process whose proxy thread died would stay up forwarding nothing: the caller ends
        it, so that its supervisor sees a failure and starts it again."""
        if self._thread.is_alive() or self._stopping or not self._thread.ident:
            return None
        return self._error or "the proxy thread ended"

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stopping = True
        if self._thread.is_alive():
            self._command.send(b"TERMINATE")
            self._thread.join(5)

    def close(self) -> None:
        for s in (self.xpub, self.xsub, self.control, self._command):
            s.close()
        if self.curve is not None:
            self.curve.stop()
        self.ctx.term()


def run(args: argparse.Namespace) -> int:
    if args.hwm < 1:  # libzmq reads 0 as "no limit": a slow subscriber would grow the proxy without end
        print(f"cellbridge proxy: --hwm must be at least 1, got {args.hwm}", file=sys.stderr)
        return 2
    if (args.server_secret is None) != (args.allowed_clients is None):
        print("cellbridge proxy: --server-secret and --allowed-clients go together (CURVE needs both)",
              file=sys.stderr)
        return 2
    curve = CurveKeys(args.server_secret, args.allowed_clients) if args.server_secret else None
    try:
        proxy = Proxy(args.front, args.back, client_key=args.client_key, curve=curve, hwm=args.hwm)
    except (ValueError, zmq.ZMQError) as exc:
        print(f"cellbridge proxy: {exc}", file=sys.stderr)
        return 2
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    proxy.start()
    print(json.dumps({"proxy": "started", "front": args.front, "back": [b.endpoint for b in args.back]}),
          file=sys.stderr, flush=True)
    failure = None
    try:
        while not done.wait(0.5):
            if (failure := proxy.failure()) is not None:
                break
    finally:
        proxy.stop()
        counters = proxy.curve.counters() if proxy.curve is not None else {}
        proxy.close()
        print(json.dumps({"proxy": "failed" if failure else "stopped", **({"error": failure} if failure else {}),
                          **counters}), file=sys.stderr)
    return 1 if failure else 0
