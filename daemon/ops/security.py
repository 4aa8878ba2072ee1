"""Who may talk to the daemon: loopback by default, ZeroMQ CURVE for anything else.

The skin's data and its control endpoint (tare, rates, reset) are private to the
robot. A socket bound to loopback (or ipc://, inproc://) is reachable only from
the same host; binding anywhere else is refused unless CURVE is configured, and
then only clients whose public key lies in the allowed directory get anything
(the ZAP handler of pyzmq's ThreadAuthenticator rejects the handshake of all others).
"""

from __future__ import annotations

import contextlib
import errno
import grp
import ipaddress
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zmq
from zmq.auth import Authenticator, load_certificate, load_certificates
from zmq.auth.thread import ThreadAuthenticator

from cellbridge.errors import CellbridgeError

SECURITY_KEYS = ("server_secret_file", "allowed_clients_dir")


class SecurityError(CellbridgeError, ValueError):
    """A bind that would expose the daemon beyond this host without CURVE."""


@dataclass(frozen=True)
class CurveKeys:
    server_secret_file: Path  # written by `cellbridge keys gen`
    allowed_clients_dir: Path  # directory of allowed clients' public key files (*.key)


def load_curve(section: Mapping[str, Any] | None, *, source: str = "config",
               base_dir: Path | None = None) -> CurveKeys | None:
    """The CURVE keys of the config's ``[security]`` table, or None when it names none.

    Paths may hold environment variables (``${CREDENTIALS_DIRECTORY}/server.key_secret``
    for systemd's LoadCredential=); relative ones are taken from ``base_dir`` (the
    config file's directory). Every problem is a ValueError naming ``source`` and the key.
    """
    if not section:
        return None
    where = f"{source}: [security]"
    unknown = sorted(set(section) - set(SECURITY_KEYS))
    if unknown:
        raise ValueError(f"{where}: unknown key {unknown[0]!r} (known: {', '.join(SECURITY_KEYS)})")
    missing = [k for k in SECURITY_KEYS if k not in section]
    if missing:
        raise ValueError(f"{where}: {missing[0]} is missing (CURVE needs both {' and '.join(SECURITY_KEYS)})")
    secret, allowed = (_path(section, key, where, base_dir) for key in SECURITY_KEYS)
    try:
        _, secret_key = load_certificate(secret)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{where}: server_secret_file {str(secret)!r}: cannot read a key: {exc}") from None
    if secret_key is None:
        raise ValueError(f"{where}: server_secret_file {str(secret)!r} holds only a public key "
                         "(give the .key_secret file written by `cellbridge keys gen`)")
    mode = secret.stat().st_mode & 0o777
    if mode & 0o077:  # as ssh does: a secret others can read is no longer a secret
        raise ValueError(f"{where}: server_secret_file {str(secret)!r} is readable by group or others "
                         f"(mode {mode:04o}); make it private: chmod 600")
    if not allowed.is_dir():
        raise ValueError(f"{where}: allowed_clients_dir {str(allowed)!r} is not a directory")
    try:
        clients = load_certificates(allowed)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{where}: allowed_clients_dir {str(allowed)!r}: {exc}") from None
    if not clients:
        raise ValueError(f"{where}: allowed_clients_dir {str(allowed)!r} holds no public key file (*.key), "
                         "so no client could connect")
    return CurveKeys(secret, allowed)


def _path(section: Mapping[str, Any], key: str, where: str, base_dir: Path | None) -> Path:
    value = section[key]
    if not isinstance(value, str) or not value:
        raise ValueError(f"{where}: {key} must be a non-empty path string, got {value!r}")
    path = Path(os.path.expandvars(value))
    return path if path.is_absolute() or base_dir is None else base_dir / path


def endpoint_error(endpoint: str, exc: zmq.ZMQError) -> str:
    """``endpoint`` and what libzmq said of it, as a sentence: one that is no endpoint at all
    (``127.0.0.1:5560``, tcp:// left out) says what an endpoint is, not libzmq's
    "Invalid argument (addr='127.0.0.1:5560')"."""
    reason = zmq.strerror(exc.errno) if exc.errno is not None else str(exc)
    if exc.errno in (errno.EINVAL, zmq.EPROTONOSUPPORT):
        return f"{endpoint}: {reason}: not a ZeroMQ endpoint (tcp://HOST:PORT or ipc://PATH)"
    return f"{endpoint}: {reason}"


def is_loopback(endpoint: str) -> bool:
    """True when a socket bound to ``endpoint`` is reachable from this host only.

    ipc:// and inproc:// are local by nature; tcp:// only on a loopback address,
    ``localhost`` or the ``lo`` interface. Anything else (``*``, 0.0.0.0, other
    transports, names we cannot judge) counts as exposed.
    """
    transport, sep, rest = endpoint.partition("://")
    if not sep:
        return False
    if transport in ("ipc", "inproc"):
        return True
    if transport not in ("tcp", "ws"):
        return False
    host = rest.split("/", 1)[0].rpartition(":")[0]
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    if host in ("localhost", "lo"):
        return True
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return False
    mapped = getattr(address, "ipv4_mapped", None)
    return address.is_loopback or (mapped is not None and mapped.is_loopback)


def check_bind(endpoint: str, curve: CurveKeys | None) -> None:
    """Refuse to bind beyond loopback unless CURVE keys are configured."""
    if curve is None and not is_loopback(endpoint):
        raise SecurityError(
            f"refusing to bind {endpoint!r}: it is not a loopback endpoint, so other hosts could reach it, "
            "and no CURVE keys are configured; bind to 127.0.0.1 or ipc://, or set server_secret_file and "
            "allowed_clients_dir in [security] (create keys with `cellbridge keys gen`)")


def restrict_ipc(endpoint: str, mode: int, group: str) -> None:
    """After binding an ipc:// endpoint: give its socket file ``mode`` and ``group``.

    A unix socket admits whoever may write its file. It is created under the process's
    umask (the unit's 0027: owner only), then opened up to exactly ``mode`` for ``group``
    (empty: the daemon's own), so that group's members, and no one else, may connect.
    tcp://, inproc:// and abstract (``ipc://@name``) endpoints have no file: nothing to do.
    OSError (for instance a group the daemon is not a member of) names the path.
    """
    transport, _, path = endpoint.partition("://")
    if transport != "ipc" or not path or path.startswith("@"):
        return
    try:
        if group:
            os.chown(path, -1, grp.getgrnam(group).gr_gid)
        os.chmod(path, mode)
    except (OSError, KeyError) as exc:
        raise SecurityError(f"{endpoint}: cannot give the socket file mode {mode:04o} and group "
                            f"{group or '(own)'!r}: {exc} (the daemon must be a member of the group: "
                            "SupplementaryGroups= in the unit)") from None


class CurveServer:
    """Makes sockets CURVE servers whose clients must hold an allowed key.

    Owns pyzmq's ThreadAuthenticator: a ZAP handler on its own thread, which
    libzmq asks about every CURVE handshake on the context's sockets. The handler
    calls :meth:`callback`, so each accepted and denied handshake is counted
    (:meth:`counters`, for the daemon's health topic).
    """

    def __init__(self, context: zmq.Context, curve: CurveKeys) -> None:
        self.curve = curve
        self._public, self._secret = _read_key(curve.server_secret_file, secret=True)
        self.allowed: frozenset[bytes] = frozenset()
        self.accepted = 0
        self.denied = 0
        self.reload()
        self._auth = ThreadAuthenticator(context)
        self._auth.start()
        self._auth.configure_curve_callback(domain="*", credentials_provider=self)

    @property
    def public_key(self) -> bytes:
        """The server's public key (Z85): what clients set as their server key."""
        return self._public

    def reload(self) -> None:
        """Read the allowed clients' directory again (on SIGHUP, after adding or removing a key).

        On a bad directory or key file the previous keys stay in force and a
        ValueError names the problem.
        """
        directory = self.curve.allowed_clients_dir
        try:
            self.allowed = frozenset(load_certificates(directory))  # one assignment: the ZAP thread sees old or new
        except (OSError, ValueError) as exc:
            raise ValueError(f"allowed_clients_dir {str(directory)!r}: {exc}") from None

    def callback(self, domain: str, client_key: bytes) -> bool:
        """ZAP thread: may the client with this public key (Z85) connect?"""
        if client_key in self.allowed:
            self.accepted += 1
            return True
        self.denied += 1
        return False

    def counters(self) -> dict[str, int]:
        return {"allowed_keys": len(self.allowed), "handshakes_accepted": self.accepted,
                "handshakes_denied": self.denied}

    def apply(self, socket: zmq.Socket) -> None:
        """Make ``socket`` a CURVE server (call before bind)."""
        socket.curve_secretkey = self._secret
        socket.curve_publickey = self._public
        socket.curve_server = True

    def stop(self, timeout: float = 2.0) -> bool:
        """End the ZAP thread; whether it ended within ``timeout`` s.

        pyzmq's own stop sends TERMINATE on a PAIR pipe and joins the thread without a
        bound: a ZAP thread that died (its end of the pipe closed) left the send blocked,
        and the daemon hung at its stop until the service manager killed it. Here the
        send does not block and the join is bounded; a thread that did not end is left
        (a daemon thread: the process still exits)."""
        auth = self._auth
        thread, pipe = auth.thread, auth.pipe
        ended = True
        if pipe is not None:
            with contextlib.suppress(zmq.ZMQError):  # (zmq.Again: nobody reads the pipe any more)
                pipe.send(b"TERMINATE", zmq.NOBLOCK)
            if thread is not None:
                thread.join(timeout)
                ended = not thread.is_alive()
            pipe.close(linger=0)
            auth.pipe = None  # type: ignore[assignment]  # (pyzmq's stop does the same)
            auth.thread = None  # type: ignore[assignment]
        Authenticator.stop(auth)  # the ZAP socket
        return ended


def apply_client(socket: zmq.Socket, server_public_file: Path, client_secret_file: Path) -> None:
    """Make ``socket`` a CURVE client of a daemon (call before connect).

    ``server_public_file`` is the daemon's ``.key`` file, ``client_secret_file``
    this client's ``.key_secret`` file (its ``.key`` must be in the daemon's
    allowed_clients_dir). ValueError naming the file for a bad one.
    """
    server_public = _read_key(server_public_file, secret=False)
    client_public, client_secret = _read_key(client_secret_file, secret=True)
    socket.curve_serverkey = server_public
    socket.curve_publickey = client_public
    socket.curve_secretkey = client_secret


def _read_key(path: Path, *, secret: bool) -> Any:
    try:
        public, secret_key = load_certificate(path)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read a CURVE key: {exc}") from None
    if not secret:
        return public
    if secret_key is None:
        raise ValueError(f"{path}: holds no secret key (give the .key_secret file)")
    return public, secret_key
