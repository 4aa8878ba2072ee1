"""A program on a pseudo-terminal of a given size, every byte it writes kept: what a
terminal would receive (the escape sequences too), for ``cellbridge watch`` tests.

Unlike tmux, nothing interprets the bytes: a test sees exactly what the view wrote.
:func:`escape_sequences` splits that stream into the control sequences a terminal would
act on (ECMA-48: CSI, OSC, DCS and the other string controls, two-byte escapes, C1 and
C0 controls), so a test can compare them with what the view itself emits.
"""

from __future__ import annotations

import fcntl
import os
import re
import signal
import struct
import subprocess
import termios
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

# CSI: ESC [ params intermediates final; OSC/DCS/SOS/PM/APC: ESC ] P X ^ _ ... ST or BEL;
# other escapes: ESC + one byte (with intermediates). C1 as characters (U+0080..U+009F) too.
_SEQ = re.compile(
    r"\x1b\[[0-?]*[ -/]*[@-~]"  # CSI
    r"|\x1b[\]PX^_][^\x07\x1b]*(?:\x07|\x1b\\)?"  # string controls, ended by BEL or ST (or cut off)
    r"|\x1b[ -/]*[0-~]"  # two-byte (and nF) escapes
    r"|\x1b"  # a lone ESC
    r"|[\x80-\x9f]"  # C1 controls
    r"|[\x00-\x08\x0b-\x0c\x0e-\x1a\x1c-\x1f\x7f]"  # C0 controls but TAB, LF, CR (and ESC, above)
)


def escape_sequences(text: str) -> Iterator[str]:
    """Every control sequence in ``text`` (decoded output of a program), in order."""
    for m in _SEQ.finditer(text):
        yield m.group(0)


class PtyProgram:
    """``argv`` on a new pty of ``cols`` × ``rows``, in its own session; :attr:`output`
    grows with every byte written to the terminal."""

    def __init__(self, argv: list[str], cols: int = 80, rows: int = 24, env: dict[str, str] | None = None) -> None:
        self.master, slave = os.openpty()
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", rows, cols, 0, 0))
        full_env = dict(os.environ, TERM="xterm-256color", COLORTERM="truecolor", **(env or {}))
        self.proc = subprocess.Popen(argv, stdin=slave, stdout=slave, stderr=slave, env=full_env,
                                     start_new_session=True, close_fds=True)
        os.close(slave)
        self.output = bytearray()
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, name="pty reader", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while True:
            try:
                data = os.read(self.master, 65536)
            except OSError:  # EIO: the program's side closed
                return
            if not data:
                return
            with self._lock:
                self.output += data

    def text(self) -> str:
        with self._lock:
            return self.output.decode("utf-8", "replace")

    def wait_for(self, pattern: str, timeout: float = 30.0, since: int = 0) -> None:
        """Until ``pattern`` (a regex) appears in the output from byte ``since`` on."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            with self._lock:
                seen = self.output[since:].decode("utf-8", "replace")
            if re.search(pattern, seen):
                return
            if self.proc.poll() is not None:
                raise AssertionError(f"the program exited ({self.proc.returncode}) before showing {pattern!r}:\n"
                                     f"{seen[-2000:]!r}")
            time.sleep(0.05)
        raise AssertionError(f"never showed {pattern!r} within {timeout} s:\n{seen[-2000:]!r}")

    def send(self, data: bytes) -> None:
        os.write(self.master, data)

    def stop(self) -> None:
        """SIGTERM to the program's session, SIGKILL after 10 s; the reader drained."""
        if self.proc.poll() is None:
            try:
                os.killpg(self.proc.pid, signal.SIGTERM)
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
            except ProcessLookupError:
                pass
        self._reader.join(5)
        try:
            os.close(self.master)
        except OSError:
            pass


@contextmanager
def pty_program(argv: list[str], cols: int = 80, rows: int = 24) -> Iterator[PtyProgram]:
    prog = PtyProgram(argv, cols, rows)
    try:
        yield prog
    finally:
        prog.stop()
