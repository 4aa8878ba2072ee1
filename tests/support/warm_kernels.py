"""Compile the numba kernels into their cache, once, before the suite's workers start.

Run by ``make test`` beside lint, and by tests/conftest.py as the controller of a
distributed run: on a fresh checkout every worker (and every daemon a live test starts)
that reaches a kernel first compiles it, about 30 s of one core, and the workers get there
together. With the cache full each loads them in a second. A warm-up that fails changes
nothing: the test that needs the kernel fails and says why.
"""

from __future__ import annotations

from cellbridge.daemon.core import readout_columns

from cellbridge.demo import _warm_kernels


def main() -> None:
    """The demo's warm-up (the contact fit's kernels, the calibrator's step) and the READOUT reader."""
    _warm_kernels()
    readout_columns.warm_up()


if __name__ == "__main__":
    main()
