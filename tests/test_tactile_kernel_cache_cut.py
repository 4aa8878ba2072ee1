"""A kernel whose cache file was cut short is compiled again, not broken for good.

numba writes a cache file to a temporary name and renames it, without syncing it: a power loss
soon after (a robot switched off) can leave the renamed file empty. numba read such an index or
data file as a cache, and raised from the kernel's every call (``EOFError``), in every process,
until someone deleted the cache: the calibrator's step unavailable, the estimator failing every
estimate, and the daemon's warm-ups starting a child at every start that failed the same way
(:mod:`cellbridge.daemon.shell.kernels`). Each case runs a small kernel of its own
(:func:`cellbridge.tactile._jit.compiled`) in fresh Pythons on a cache folder of its own.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

KERNEL = """
from cellbridge.tactile._jit import compiled

@compiled
def plus_one(x):
    return x + 1.0
"""

SCRIPT = r"""
import tiny_kernel
from cellbridge.tactile import _jit
print("missing", ",".join(_jit.missing_from_cache()) or "-")
print("value", tiny_kernel.plus_one(1.0))
print("loaded", len(tiny_kernel.plus_one.stats.cache_hits))
"""


def _run(tmp_path: Path) -> dict[str, str]:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"),
               PYTHONPATH=os.pathsep.join(p for p in [str(tmp_path / "src"), os.environ.get("PYTHONPATH")] if p))
    env.pop("NUMBA_CACHE_LOCATOR_CLASSES", None)
    r = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return dict(line.split(" ", 1) for line in r.stdout.splitlines())


@pytest.mark.parametrize("suffix", ["nbi", "nbc"])
def test_a_cache_file_cut_short_is_compiled_again_and_rewritten(tmp_path: Path, suffix: str) -> None:
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "tiny_kernel.py").write_text(KERNEL)
    first = _run(tmp_path)
    assert first["value"] == "2.0" and first["loaded"] == "0"
    assert _run(tmp_path)["loaded"] == "1"  # (cached)
    [cut] = (tmp_path / "cache").rglob(f"tiny_kernel.plus_one-*.{suffix}")
    cut.write_bytes(b"")
    broken = _run(tmp_path)
    assert broken["value"] == "2.0" and broken["loaded"] == "0"  # compiled again
    if suffix == "nbi":
        assert broken["missing"] == "tiny_kernel.plus_one"  # (and not read as a cache)
    again = _run(tmp_path)
    assert again["missing"] == "-" and again["value"] == "2.0" and again["loaded"] == "1"  # rewritten
