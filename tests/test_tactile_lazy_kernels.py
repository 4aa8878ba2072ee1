"""What needs only the physics, the layout or the calibration does not load numba.

numba needs executable memory, which a service unit's ``MemoryDenyWriteExecute=yes``
forbids (``import numba`` raises PermissionError there), and costs time at start-up.
The emulated mesh (``cellbridge.tactile.transfer``), the daemon's configuration
(``cellbridge.config`` → ``cellbridge.tactile.layout``) and the CLI's ``--help`` must
not pay for the contact estimator's kernels.
"""

from __future__ import annotations

import subprocess
import sys

SCRIPT = r"""
import sys
import cellbridge.config, cellbridge.cli
import cellbridge.tactile
from cellbridge.tactile import Calibrator, Contact, cluster_elements, grid_layout, skin_response
from cellbridge.tactile.transfer import counter_delta
import cellbridge.emulator.chip.chip
print("numba loaded early", "numba" in sys.modules)
from cellbridge.tactile import ContactEstimator, ContactTracker, TrackedContact, estimate_contacts
lay = grid_layout(2, 2)
c, = ContactEstimator(lay).estimate(*skin_response(lay, [[0.02, 0.0, 3.0, 0.012]]))
print("estimate", round(c.x, 6), round(c.force, 6), "numba" in sys.modules)
print("all", sorted(set(cellbridge.tactile.__all__) - set(dir(cellbridge.tactile)) - set(cellbridge.tactile._LAZY)))
"""


def test_physics_layout_and_calibration_import_without_numba_and_estimator_loads_on_use():
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    out = r.stdout.splitlines()
    assert out[0] == "numba loaded early False"
    assert out[1] == "estimate 0.02 3.0 True"
    assert out[2] == "all []"  # every exported name resolves


def test_unknown_attribute_is_an_attribute_error():
    import cellbridge.tactile as t

    try:
        t.NoSuchThing  # noqa: B018
    except AttributeError as exc:
        assert "NoSuchThing" in str(exc)
    else:
        raise AssertionError("no AttributeError")


MDWE_SCRIPT = r"""
import ctypes, sys
libc = ctypes.CDLL(None, use_errno=True)
# PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN: what systemd applies for MemoryDenyWriteExecute=yes.
if libc.prctl(65, 1, 0, 0, 0) != 0:
    print("no mdwe")
    sys.exit(0)
import cellbridge.config, cellbridge.cli
from cellbridge.tactile import Calibrator, grid_layout, parse_layout, skin_response
from cellbridge.tactile.transfer import counter_delta
import cellbridge.emulator.chip.chip
print("imported")
"""


def test_physics_layout_and_cli_import_where_executable_memory_is_denied():
    r = subprocess.run([sys.executable, "-c", MDWE_SCRIPT], capture_output=True, text=True, timeout=120)
    if r.stdout.strip() == "no mdwe":
        import pytest

        pytest.skip("this kernel has no PR_SET_MDWE (Linux < 6.3)")
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "imported"
