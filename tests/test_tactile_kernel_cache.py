"""The compiled kernels where numba has no writable cache folder (a read-only install).

The daemon's unit makes the installation read-only and hides every home folder
(``ProtectSystem=strict``, ``ProtectHome=yes``, ``DynamicUser=yes``). numba then
finds no place for its cache and, with ``cache=True``, refuses the decorator at
import time. ``NUMBA_CACHE_LOCATOR_CLASSES`` offering only the zip-file locator
puts a normal installation in the same state without root or mounts (checked by
hand in a read-only bind mount with a read-only HOME: same error, same fix).
"""

from __future__ import annotations

import os
import subprocess
import sys

SCRIPT = r"""
import warnings
warnings.simplefilter("always")
with warnings.catch_warnings(record=True) as caught:
    import cellbridge.config  # what the daemon imports to read its layout
    import cellbridge.tactile.estimator  # the estimator's modules: every kernel
    from cellbridge.tactile import _jit
    from cellbridge.tactile.disk_model import sensitivity_slope
print("uncached", len(_jit.UNCACHED))
print("warnings", sum("NUMBA_CACHE_DIR" in str(w.message) for w in caught))
g, e = sensitivity_slope(1000.0, 1e5, 1e-3, 1e-4, 1e-11)
print("kernel", g == g)
"""


def test_import_without_a_writable_numba_cache_folder_compiles_uncached_and_says_so():
    env = dict(os.environ, NUMBA_CACHE_LOCATOR_CLASSES="ZipCacheLocator")
    env.pop("NUMBA_CACHE_DIR", None)
    r = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    lines = dict(line.split(" ", 1) for line in r.stdout.splitlines())
    assert int(lines["uncached"]) >= 20  # every kernel, named
    assert lines["warnings"] == "1"  # one warning, naming the remedy
    assert lines["kernel"] == "True"  # and the kernels still run


def test_kernels_are_cached_where_a_cache_folder_is_writable(tmp_path):
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path))
    env.pop("NUMBA_CACHE_LOCATOR_CLASSES", None)
    r = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "uncached 0" in r.stdout and "warnings 0" in r.stdout
    assert any(p.suffix == ".nbi" for p in tmp_path.rglob("*"))
