"""A Python script run in a fresh process with its own numba cache folder: what a fresh
installation (an empty folder) or a later start (the same folder again) does with the kernels."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path


def run_with_cache(script: str, mode: str, cache: Path) -> dict[str, str]:
    """``script`` run as ``python -c script mode`` with ``NUMBA_CACHE_DIR=cache``; its output's
    lines ``key value`` as a dict. AssertionError with its stderr's tail when it fails."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    env.pop("NUMBA_CACHE_LOCATOR_CLASSES", None)
    r = subprocess.run([sys.executable, "-c", script, mode], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return dict(line.split(" ", 1) for line in r.stdout.splitlines())
