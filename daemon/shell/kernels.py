"""The daemon's compiled kernels compiled in a child process when their cache is empty.

A process that compiles numba kernels keeps LLVM's memory for its life: on a fresh
installation (or after an upgrade) the daemon, compiling the READOUT reader and the
calibrator's step in its own process, and its contact worker, compiling the fit's
kernels, each stayed about 100 MiB larger than the same processes loading the same
kernels from the cache, until they were restarted; a robot's daemon may not be for days
(``bench/bench_humanoid_soak.py`` with an empty ``NUMBA_CACHE_DIR`` shows it). So where a kernel
is not in the cache, the warm-up runs first in a short-lived child Python that compiles
it into the cache, and the process then loads it from there. Where the cache already
holds every kernel nothing is started; where there is no disk cache
(:data:`cellbridge.tactile._jit.UNCACHED`) a child would compile for nothing, and the
process compiles in place as before.
"""

from __future__ import annotations

import os
import subprocess
import sys

from cellbridge.tactile import _jit

#: Longest a child's compile may take (s): about 20 s of one core on a fresh installation,
#: much longer on a loaded machine; past it the caller compiles in its own process.
COMPILE_LIMIT = 300.0


#: The child's first lines after its import path (``{parent}``: the caller's pid): a thread
#: that ends the child once its parent is gone (no longer its parent's pid).
_ORPHAN_WATCH = """import os, threading, time
def _watch():
    while os.getppid() == {parent}:
        time.sleep(0.5)
    os._exit(1)
threading.Thread(target=_watch, daemon=True).start()
"""


def compile_apart(target: str, limit: float = COMPILE_LIMIT, modules: tuple[str, ...] = ()) -> bool:
    """Run ``target`` (``"package.module:function"``, a warm-up taking no argument) in a
    child Python when a kernel made in this process is missing from the disk cache, and
    wait for it (at most ``limit`` s). With ``modules``, only the kernels of those modules
    are asked for: the ones the warm-up loads, made in this process before the call (the
    daemon holds its contact worker's kernels, which no warm-up of its own compiles: asked
    for too, they started a child at every start of a daemon without contacts).

    Returns whether a child ran and succeeded (its kernels are then in the cache). Not an
    error otherwise: a child that cannot start, fails or overruns (it is killed) leaves
    the caller's own warm-up to compile in place, as without this step. The child stays in
    the caller's process group, so that a stop of the group stops it too, and ends itself
    within half a second when the caller is gone (killed alone, it would have compiled on)."""
    module, _, function = target.partition(":")
    if not module or not function.isidentifier():
        raise ValueError(f"compile target {target!r}: must be 'package.module:function'")
    if _jit.UNCACHED or not _jit.missing_from_cache(modules):
        return False
    # (the caller's import path, not the one `python -c` makes: the working folder first, where
    # another `cellbridge` may be, a checkout's: the child must compile the caller's files)
    code = (f"import sys; sys.path[:] = {sys.path!r}\n" + _ORPHAN_WATCH.format(parent=os.getpid())
            + f"import importlib; importlib.import_module({module!r}).{function}()\n")
    try:
        done = subprocess.run([sys.executable, "-c", code], stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL, timeout=limit, check=False)
    except (OSError, subprocess.SubprocessError):  # (a timeout kills the child)
        return False
    return done.returncode == 0


def warm_up() -> None:
    """The contact worker's warm-up, run in the worker process: the estimator's kernels
    compiled apart where the cache lacks them, then :func:`cellbridge.daemon.core.contacts.warm_up`
    (imports, the kernels loaded)."""
    from cellbridge.daemon.core import contacts

    compile_apart("cellbridge.daemon.core.contacts:warm_up")
    contacts.warm_up()
