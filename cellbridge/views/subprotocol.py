"""Both names of the Foxglove WebSocket protocol on one port: ``foxglove.sdk.v1`` and ``foxglove.websocket.v1``.

The protocol (spec: github.com/foxglove/ws-protocol, ``docs/spec.md``) was named
``foxglove.websocket.v1``; since the Foxglove SDK replaced the ws-protocol libraries it is
named ``foxglove.sdk.v1``, with the same messages. Today's Foxglove app offers the new
name (that is how it reaches foxglove_bridge 3.x and every SDK server); older Foxglove
Studio releases, Lichtblick before it added the new name, and clients built on the
ws-protocol libraries offer only the old one. The SDK's server (``foxglove-sdk``, its
Rust handshake) answers a client that does not offer ``foxglove.sdk.v1`` with HTTP 400,
and has no setting for another name.

So ``cellbridge foxglove`` puts this front on its port: it reads each connection's
upgrade request, and where the client offers only the old name it offers the new one to
the SDK server (listening on a loopback port of its own) and, in the server's answer,
names the old one back: the client gets the subprotocol it asked for, RFC 6455's rule.
The accept key does not depend on the subprotocol, so nothing else changes; after the
two heads, bytes pass through untouched both ways. A client offering the new name (or
neither) passes unchanged, and the SDK server answers it as it would directly.

The front is also where a connection is admitted (:mod:`cellbridge.views.access`): a
request whose ``Host`` is not a name of this machine's loopback (DNS rebinding) or whose
``Origin`` is another site's page (cross-site WebSocket hijacking) is answered 403 and
never reaches the SDK's server. Programs (the Foxglove desktop app) send no ``Origin``
and pass; a browser page only from the origins allowed (Foxglove's web app by default).

:func:`rewrite_request` and :func:`rewrite_response` are the pure core (bytes in, bytes
out), :func:`refusal` the admission; :class:`SubprotocolFront` is the asyncio shell, in
a thread of its own.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Iterable

from cellbridge.views.access import host_allowed, origin_allowed

SDK = "foxglove.sdk.v1"
LEGACY = "foxglove.websocket.v1"
HEADER = b"sec-websocket-protocol"
MAX_HEAD = 16 * 1024  #: longest HTTP head taken (a browser's upgrade request is well under 2 kB)
HEAD_TIMEOUT = 10.0  #: s a client or the server has to send its head


def header(head: bytes, name: str) -> str | None:
    """The value of header ``name`` in an HTTP head (the first, if repeated), or None."""
    want = name.lower().encode()
    for line in head.split(b"\r\n")[1:]:
        key, sep, value = line.partition(b":")
        if sep and key.strip().lower() == want:
            return value.strip().decode("latin-1")
    return None


def refusal(head: bytes, origins: Iterable[str] = (), hosts: Iterable[str] = ()) -> bytes | None:
    """The 403 answer to an upgrade request this server does not admit, or None to admit it:
    ``Host`` must name this machine (a loopback name, an IP address, or one of ``hosts``)
    and ``Origin``, when there is one, be one of ``origins`` or the server's own."""
    host = header(head, "host")
    if not host_allowed(host, hosts):
        why = "this server does not answer to that host name"
    elif not origin_allowed(header(head, "origin"), host, origins):
        why = "connections from this origin are not allowed (cellbridge foxglove --allow-origin)"
    else:
        return None
    body = f"403: {why}\n".encode()
    return (b"HTTP/1.1 403 Forbidden\r\nContent-Type: text/plain; charset=utf-8\r\n"
            b"Content-Length: " + str(len(body)).encode() + b"\r\nConnection: close\r\n\r\n" + body)


def offered(head: bytes) -> list[str]:
    """The subprotocols an upgrade request (or its answer) names, in order."""
    names: list[str] = []
    for line in head.split(b"\r\n")[1:]:
        name, sep, value = line.partition(b":")
        if sep and name.strip().lower() == HEADER:
            names += [v.strip() for v in value.decode("latin-1").split(",") if v.strip()]
    return names


def rewrite_request(head: bytes) -> tuple[bytes, bool]:
    """(the head to pass to the SDK server, whether the client offered only the old name).

    A request offering :data:`LEGACY` but not :data:`SDK` has its subprotocol header(s)
    replaced by one that offers :data:`SDK`; any other passes unchanged."""
    names = offered(head)
    if SDK in names or LEGACY not in names:
        return head, False
    out: list[bytes] = []
    replaced = False
    for i, line in enumerate(head.split(b"\r\n")):
        name, sep, _ = line.partition(b":")
        if i > 0 and sep and name.strip().lower() == HEADER:
            if not replaced:
                out.append(b"Sec-WebSocket-Protocol: " + SDK.encode())
                replaced = True
            continue
        out.append(line)
    return b"\r\n".join(out), True


def rewrite_response(head: bytes, legacy: bool) -> bytes:
    """The SDK server's answer as the client must see it: for a client of the old name,
    the chosen subprotocol named :data:`LEGACY`; otherwise unchanged."""
    if not legacy:
        return head
    out = []
    for i, line in enumerate(head.split(b"\r\n")):
        name, sep, value = line.partition(b":")
        if i > 0 and sep and name.strip().lower() == HEADER and value.strip() == SDK.encode():
            line = name + b": " + LEGACY.encode()
        out.append(line)
    return b"\r\n".join(out)


class SubprotocolFront:
    """Listens on ``host:port`` and passes every connection it admits (:func:`refusal`,
    with ``origins`` and ``hosts``) to the SDK server on ``127.0.0.1:upstream_port``, heads
    rewritten as above. :attr:`port` is the port bound (``port`` 0: a free one);
    :attr:`connections`, :attr:`legacy` and :attr:`refused` count what came in. OSError
    from the constructor when it cannot listen."""

    def __init__(self, host: str, port: int, upstream_port: int, origins: Iterable[str] = (),
                 hosts: Iterable[str] = ()) -> None:
        self.upstream_port = upstream_port
        self.origins = tuple(origins)
        self.hosts = (host, *hosts)
        self.connections = 0
        self.legacy = 0
        self.refused = 0
        self.port = 0
        self._loop = asyncio.new_event_loop()
        self._server: asyncio.AbstractServer | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._server = self._loop.run_until_complete(
            asyncio.start_server(self._handle, host, port, limit=MAX_HEAD))
        self.port = self._server.sockets[0].getsockname()[1]
        self._thread = threading.Thread(target=self._loop.run_forever, name="foxglove-front", daemon=True)
        self._thread.start()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        upstream: asyncio.StreamWriter | None = None
        try:
            self.connections += 1
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT)
            refused = refusal(head, self.origins, self.hosts)
            if refused is not None:
                self.refused += 1
                writer.write(refused)
                await writer.drain()
                return
            head, legacy = rewrite_request(head)
            self.legacy += legacy
            up_reader, upstream = await asyncio.open_connection("127.0.0.1", self.upstream_port, limit=MAX_HEAD)
            upstream.write(head)
            answer = await asyncio.wait_for(up_reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT)
            writer.write(rewrite_response(answer, legacy))
            await asyncio.gather(_pipe(reader, upstream), _pipe(up_reader, writer))
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError):
            pass  # a client gone, a head too long or too slow: that connection ends, no other
        except asyncio.CancelledError:
            pass  # the front is closing (close()): this connection ends with it, quietly
        finally:
            for w in (writer, upstream):
                if w is not None:
                    w.close()
            self._tasks.discard(task)

    def close(self, grace: float = 0.0) -> None:
        """Stop listening, end every connection, and stop the thread. Connections get
        ``grace`` s to end by themselves first: the SDK server, stopped before, sends each
        client a close frame through them."""
        async def shutdown() -> None:
            if self._server is not None:
                self._server.close()
            if self._tasks and grace > 0:
                await asyncio.wait(list(self._tasks), timeout=grace)
            for t in list(self._tasks):
                t.cancel()
            await asyncio.gather(*self._tasks, return_exceptions=True)

        if self._thread.is_alive():
            asyncio.run_coroutine_threadsafe(shutdown(), self._loop).result(5 + grace)
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(5)
        self._loop.close()


async def _pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
    """Copy until ``src`` ends, then end ``dst``'s sending side."""
    try:
        while data := await src.read(65536):
            dst.write(data)
            await dst.drain()
    finally:
        with contextlib.suppress(OSError):
            if dst.can_write_eof():
                dst.write_eof()
