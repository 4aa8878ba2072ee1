"""The demo (and the live-skin tests) read the gateway's device off ``mesh up``'s output:
within GATEWAY_TIMEOUT, whatever ``mesh up`` does."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest

import cellbridge.demo as demo


@contextlib.contextmanager
def _child(code: str) -> Iterator[subprocess.Popen[str]]:
    """A stand-in for 'mesh up' running ``code``; killed and reaped on exit."""
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, start_new_session=True)
    try:
        yield proc
    finally:
        proc.kill()
        proc.wait()
        assert proc.stdout is not None
        proc.stdout.close()


def test_a_silent_mesh_up_is_given_up_on_at_the_timeout(monkeypatch: pytest.MonkeyPatch) -> None:
    """A 'mesh up' that lives on and prints nothing: a blocking line read waited for ever."""
    monkeypatch.setattr(demo, "GATEWAY_TIMEOUT", 1.0)
    with _child("import time; time.sleep(30)") as proc:
        t0 = time.monotonic()
        with pytest.raises(RuntimeError, match="named no gateway within"):
            demo.gateway_line(proc)
        assert time.monotonic() - t0 < 5.0


def test_the_gateway_line_is_found_when_it_comes_in_pieces_after_other_lines() -> None:
    with _child("import sys, time\n"
                "sys.stdout.write('starting\\ngate'); sys.stdout.flush(); time.sleep(0.3)\n"
                "sys.stdout.write('way 1 /dev/pts/9\\n'); sys.stdout.flush(); time.sleep(30)") as proc:
        assert demo.gateway_line(proc)[:3] == ["gateway", "1", "/dev/pts/9"]


def test_a_mesh_up_that_ends_first_is_reported_with_its_status() -> None:
    with _child("import sys; print('cannot start'); sys.exit(3)") as proc, \
            pytest.raises(RuntimeError, match=r"ended \(status 3\)"):
        demo.gateway_line(proc)
