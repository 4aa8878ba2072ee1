"""The subscriber examples of examples/ as commands a test runs: the Python one as it is, the C one
built with its Makefile, the JavaScript one with node (each skips, saying why, where it cannot run)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
JS_DIR = EXAMPLES / "javascript"


def _pkg_config_ok(*packages: str) -> bool:
    return shutil.which("pkg-config") is not None and subprocess.run(
        ["pkg-config", "--exists", *packages], capture_output=True).returncode == 0


def c_subscriber(tmp_path: Path) -> list[str]:
    if shutil.which("cc") is None or shutil.which("make") is None:
        pytest.skip("C example: no C compiler (cc) or make on this machine")
    if not (_pkg_config_ok("libzmq") and (_pkg_config_ok("msgpack-c") or _pkg_config_ok("msgpack"))):
        pytest.skip("C example: libzmq or msgpack-c development files are missing "
                    "(Debian: apt-get install libzmq3-dev libmsgpack-dev; `make test` run as root installs them)")
    build = tmp_path / "c"
    shutil.copytree(EXAMPLES / "c", build)
    (build / "subscriber").unlink(missing_ok=True)
    out = subprocess.run(["make", "-C", str(build)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "warning" not in out.stderr
    return [str(build / "subscriber")]


def js_subscriber(tmp_path: Path) -> list[str]:
    node = shutil.which("node")
    if node is None:
        pytest.skip("JavaScript example: node is not installed")
    probe = subprocess.run([node, "-e", "require('zeromq'); require('@msgpack/msgpack')"],
                           cwd=JS_DIR, capture_output=True, timeout=60)
    if probe.returncode != 0:
        pytest.skip("JavaScript example: npm packages zeromq and @msgpack/msgpack are not installed "
                    "(run `npm install` in examples/javascript; the suite downloads nothing)")
    return [node, str(JS_DIR / "subscriber.js")]


def py_subscriber(tmp_path: Path) -> list[str]:
    return [sys.executable, str(EXAMPLES / "python" / "subscriber.py")]
