"""Suite-wide settings.

Hypothesis's per-example deadline is a timed assertion: on a shared two-core machine (CI,
a laptop running the emulator) a slow example says nothing about the code, so the
deadline is off everywhere; speed is measured by the scripts in bench/.
"""

import pytest
from hypothesis import settings

settings.register_profile("cellbridge", deadline=None)
settings.load_profile("cellbridge")


@pytest.fixture
def warm_kernels() -> None:
    """The contact estimator's kernels in numba's cache before a test's contact worker
    needs them: on a fresh checkout its warm-up compiles them (half a minute, more on a
    loaded machine), and a test that waits for its contacts outlasts its own patience."""
    from cellbridge.demo import _warm_kernels

    _warm_kernels()
