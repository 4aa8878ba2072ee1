"""``cellbridge foxglove`` takes the Foxglove protocol under both its names.

The heads' rewriting as a pure function, then the front before a real foxglove-sdk
server in this process, reached by a real WebSocket client on loopback: a client of the
protocol's former name (``foxglove.websocket.v1``) is answered with that name and gets
the server's messages; one of the new name passes as it would directly; one offering
neither is refused by the SDK server as directly (HTTP 400).
"""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest

from cellbridge.views.subprotocol import (
    LEGACY,
    SDK,
    SubprotocolFront,
    offered,
    rewrite_request,
    rewrite_response,
)

REQUEST = (b"GET / HTTP/1.1\r\nHost: 127.0.0.1:8765\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
           b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n%s\r\n")


def request(*protocol_lines: bytes) -> bytes:
    return REQUEST % b"".join(line + b"\r\n" for line in protocol_lines)


def test_a_request_of_the_former_name_only_offers_the_sdk_name_and_nothing_else_changes() -> None:
    head = request(b"Sec-WebSocket-Protocol: " + LEGACY.encode())
    out, legacy = rewrite_request(head)
    assert legacy and offered(out) == [SDK]
    assert out.replace(SDK.encode(), LEGACY.encode()) == head
    # several headers, other names, any case: one header offering the SDK's name instead
    head = request(b"sec-websocket-protocol: x.other", b"SEC-WEBSOCKET-PROTOCOL: " + LEGACY.encode())
    out, legacy = rewrite_request(head)
    assert legacy and offered(out) == [SDK] and out.endswith(b"\r\n\r\n") and b"Sec-WebSocket-Key" in out


@pytest.mark.parametrize("lines", [[b"Sec-WebSocket-Protocol: " + SDK.encode()],
                                   [b"Sec-WebSocket-Protocol: " + f"{SDK}, {LEGACY}".encode()],
                                   [b"Sec-WebSocket-Protocol: other"], []])
def test_other_requests_pass_unchanged(lines: list[bytes]) -> None:
    head = request(*lines)
    assert rewrite_request(head) == (head, False)


def test_the_answer_names_the_former_name_back_only_to_its_clients() -> None:
    answer = (b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
              b"Sec-WebSocket-Accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\nsec-websocket-protocol: foxglove.sdk.v1\r\n\r\n")
    assert offered(rewrite_response(answer, True)) == [LEGACY]
    assert rewrite_response(answer, True) == answer.replace(SDK.encode(), LEGACY.encode())
    assert rewrite_response(answer, False) == answer
    refused = b"HTTP/1.1 400 Bad Request\r\ncontent-length: 46\r\n\r\n"
    assert rewrite_response(refused, True) == refused


@pytest.fixture
def front() -> Iterator[tuple[SubprotocolFront, object]]:
    import foxglove

    server = foxglove.start_server(name="front-test", host="127.0.0.1", port=0)
    channel = foxglove.Channel("/test")
    fr = SubprotocolFront("127.0.0.1", 0, server.port)
    try:
        yield fr, channel
    finally:
        fr.close()
        server.stop()


def _connect(port: int, subprotocols: list[str]):
    from websockets.sync.client import connect

    return connect(f"ws://127.0.0.1:{port}", subprotocols=subprotocols, open_timeout=10)  # type: ignore[arg-type]


@pytest.mark.parametrize("offer", [[LEGACY], [SDK], [SDK, LEGACY]])
def test_a_client_of_either_name_gets_its_name_and_the_servers_messages(front: tuple, offer: list[str]) -> None:
    fr, _ = front
    with _connect(fr.port, offer) as ws:
        assert ws.subprotocol == offer[0]
        info = json.loads(ws.recv(timeout=10))
        assert info["op"] == "serverInfo" and info["name"] == "front-test"
        adv = json.loads(ws.recv(timeout=10))
        assert adv["op"] == "advertise" and [c["topic"] for c in adv["channels"]] == ["/test"]
    assert fr.connections == 1 and fr.legacy == (offer == [LEGACY])


def test_a_client_of_neither_name_is_refused_as_the_sdk_server_refuses_it(front: tuple) -> None:
    from websockets.exceptions import InvalidStatus

    fr, _ = front
    with pytest.raises(InvalidStatus) as refused, _connect(fr.port, ["some.other.v1"]):
        pass
    assert refused.value.response.status_code == 400


def test_a_port_in_use_is_an_oserror() -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        with pytest.raises(OSError):
            SubprotocolFront("127.0.0.1", s.getsockname()[1], 1)


def test_without_the_front_the_sdk_server_refuses_the_former_name(front: tuple) -> None:
    """Why the front exists: the SDK's own server answers foxglove.websocket.v1 with 400."""
    from websockets.exceptions import InvalidStatus

    fr, _ = front
    with pytest.raises(InvalidStatus) as refused, _connect(fr.upstream_port, [LEGACY]):
        pass
    assert refused.value.response.status_code == 400
