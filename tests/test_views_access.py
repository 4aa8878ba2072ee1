"""Who may reach ``cellbridge web`` and ``cellbridge foxglove``: the Host and Origin checks
(cellbridge/views/access.py, and the Foxglove front's admission in subprotocol.py)."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cellbridge.views.access import FOXGLOVE_WEB, host_allowed, origin_allowed, split_host
from cellbridge.views.subprotocol import refusal


@pytest.mark.parametrize("host", ["127.0.0.1:8080", "localhost:8080", "LOCALHOST", "[::1]:8080", "::1",
                                  "127.0.0.2", "192.168.1.5:8080", "localhost.:8080", None])
def test_loopback_names_and_address_literals_are_allowed_hosts(host: str | None) -> None:
    assert host_allowed(host)


@pytest.mark.parametrize("host", ["evil.example", "evil.example:8080", "localhost.evil.example:8080",
                                  "127.0.0.1.evil.example", "", ":8080", "[::1", "[::1]x", "localhost:99999",
                                  "localhost:abc", "robot.local:8080"])
def test_a_name_the_view_is_not_known_by_is_refused(host: str) -> None:
    """DNS rebinding: evil.example made to resolve to 127.0.0.1 still says Host: evil.example."""
    assert not host_allowed(host)


def test_names_given_are_allowed_case_insensitively() -> None:
    assert host_allowed("Robot.Local:8080", ["robot.local"]) and host_allowed("robot", ["ROBOT"])
    assert not host_allowed("robot.local.evil.example", ["robot.local"])


def test_split_host() -> None:
    assert split_host("[::1]:8080") == ("::1", 8080) and split_host("A.b:1") == ("a.b", 1)
    assert split_host("x") == ("x", None) and split_host("x:0") == ("", None)


@pytest.mark.parametrize("origin, host, ok", [
    (None, "127.0.0.1:8080", True),  # not a browser (Foxglove desktop, websockets clients)
    ("http://127.0.0.1:8080", "127.0.0.1:8080", True),  # the page itself
    ("http://localhost:8080", "localhost:8080", True),
    ("http://[::1]:8080", "[::1]:8080", True),
    ("http://127.0.0.1", "127.0.0.1:80", True),
    ("https://127.0.0.1", "127.0.0.1", True),
    ("http://evil.example", "127.0.0.1:8080", False),  # another site's page
    ("http://127.0.0.1:8081", "127.0.0.1:8080", False),  # another port is another origin
    ("http://localhost:8080", "127.0.0.1:8080", False),
    ("https://127.0.0.1:8080.evil.example", "127.0.0.1:8080", False),
    ("null", "127.0.0.1:8080", False),  # a sandboxed frame, a file
    ("file://", "127.0.0.1:8080", False),
    ("http://127.0.0.1:8080", None, False),
    ("http://127.0.0.1:bad", "127.0.0.1:8080", False),
])
def test_only_the_pages_own_origin_may_open_the_websocket(origin: str | None, host: str | None, ok: bool) -> None:
    assert origin_allowed(origin, host) is ok


def test_listed_origins_are_allowed() -> None:
    assert origin_allowed("https://app.foxglove.dev", "127.0.0.1:8765", [FOXGLOVE_WEB])
    assert origin_allowed("HTTPS://APP.FOXGLOVE.DEV/", "localhost:8765", [FOXGLOVE_WEB])
    assert not origin_allowed("https://app.foxglove.dev.evil.example", "127.0.0.1:8765", [FOXGLOVE_WEB])
    assert not origin_allowed("http://app.foxglove.dev", "127.0.0.1:8765", [FOXGLOVE_WEB])


@given(st.text(max_size=40), st.text(max_size=40) | st.none())
def test_the_checks_never_raise(origin: str, host: str | None) -> None:
    origin_allowed(origin, host, [FOXGLOVE_WEB])
    host_allowed(host, ["robot"])


def _upgrade(host: str | None, origin: str | None) -> bytes:
    lines = [b"GET / HTTP/1.1"]
    if host is not None:
        lines.append(b"Host: " + host.encode())
    if origin is not None:
        lines.append(b"Origin: " + origin.encode())
    lines += [b"Upgrade: websocket", b"Connection: Upgrade", b"Sec-WebSocket-Protocol: foxglove.sdk.v1", b"", b""]
    return b"\r\n".join(lines)


def test_the_foxglove_front_admits_the_desktop_app_and_foxgloves_web_app_only() -> None:
    origins = (FOXGLOVE_WEB,)
    assert refusal(_upgrade("127.0.0.1:8765", None), origins) is None  # the desktop app sends no Origin
    assert refusal(_upgrade("localhost:8765", FOXGLOVE_WEB), origins) is None
    for host, origin in (("127.0.0.1:8765", "http://evil.example"), ("evil.example:8765", None),
                         ("evil.example:8765", "http://evil.example:8765")):
        answer = refusal(_upgrade(host, origin), origins)
        assert answer is not None and answer.startswith(b"HTTP/1.1 403 Forbidden\r\n")
        head, _, body = answer.partition(b"\r\n\r\n")
        assert int(dict(line.split(b": ", 1) for line in head.split(b"\r\n")[1:])[b"Content-Length"]) == len(body)


def test_a_token_file_that_cannot_be_read_is_named_in_a_sentence(tmp_path: Path) -> None:
    """`cellbridge web --token-file nope.token` said "[Errno 2] No such file or directory:
    'nope.token'", and a binary file a codec's complaint without the file's name."""
    from cellbridge.views.web import read_token

    (tmp_path / "binary.token").write_bytes(b"\xff\xfe" * 20)
    (tmp_path / "good.token").write_text("a-token-of-twenty-chars\n")
    for name, says in (("nope.token", "cannot read the token: No such file or directory"),
                       ("binary.token", "the token must be text")):
        with pytest.raises(ValueError) as exc:
            read_token(tmp_path / name)
        assert str(exc.value).startswith(f"{tmp_path / name}: {says}")
        assert "Errno" not in str(exc.value)
    assert read_token(tmp_path / "good.token") == "a-token-of-twenty-chars"
