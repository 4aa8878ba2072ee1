"""A kernel's disk cache is not used once a rule compiled into it changed in another module.

numba checks a cached kernel against its own file alone (its modification time and size).
The contact kernels compile in rules of other modules: the element inverse of
``inverse_kernel`` calls ``disk_model.layer_response`` and ``inversion``'s per-reading
rules, the fits call ``disk_model``'s and ``spread_model``'s. An edit of one of those left
the callers' cached code as it was, and every process then ran the rule from before the
edit (which one depended on the order the kernels were first called in): the suite tested
stale compiled code and said nothing.

Run on a copy of the tactile package in a folder of its own (imported as
``cellbridge.tactile``) with a cache folder of its own, so the tree and its cache are
untouched: the element inverse once, the copy's ``layer_response`` edited, then again, and
against a cold cache of the edited copy.
"""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cellbridge.tactile
from cellbridge.tactile import _jit

TACTILE = Path(cellbridge.tactile.__file__).parent

SCRIPT = r"""
import sys
from importlib.machinery import PathFinder
from importlib.util import spec_from_file_location
from pathlib import Path

COPY = sys.argv[1]


class Copy:
    @classmethod
    def find_spec(cls, name, path=None, target=None):
        if name == "cellbridge.tactile":
            return spec_from_file_location(name, Path(COPY) / "__init__.py", submodule_search_locations=[COPY])
        if name.startswith("cellbridge.tactile."):
            return PathFinder.find_spec(name, [COPY])
        return None


sys.meta_path.insert(0, Copy)
from cellbridge.tactile.inverse_kernel import solve_compiled  # (the inverse first: no callee loaded before it)
from cellbridge.tactile.element import ElementParams
from cellbridge.tactile.layout import grid_layout
from cellbridge.tactile.response import skin_response
import cellbridge.tactile.inverse_kernel as k
assert k.__file__.startswith(COPY), k.__file__
lay = grid_layout(2, 2)
d1, d2 = skin_response(lay, [(0.0, 0.0, 3.0, 0.012)])
print(repr(float(solve_compiled(d1, d2, ElementParams(side=lay.side)).force[0])))
"""

OLD = "    return _g_of(lam, one_m, d, d0, eps), _elasticity(lam, d, d0)\n"
NEW = "    return 2.0 * _g_of(lam, one_m, d, d0, eps), _elasticity(lam, d, d0)\n"


def _force(copy: Path, cache: Path) -> float:
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    env.pop("NUMBA_CACHE_LOCATOR_CLASSES", None)
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(copy)], env=env, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    return float(r.stdout.split()[-1])


def test_a_rule_edited_in_another_module_is_compiled_again_not_taken_from_the_cache(tmp_path: Path) -> None:
    copy = tmp_path / "tactile"
    shutil.copytree(TACTILE, copy, ignore=shutil.ignore_patterns("__pycache__"))
    before = _force(copy, tmp_path / "cache")
    model = copy / "disk_model.py"
    text = model.read_text()
    assert OLD in text  # (the rule this test edits: layer_response's g)
    model.write_text(text.replace(OLD, NEW))
    st = model.stat()
    os.utime(model, ns=(st.st_atime_ns, st.st_mtime_ns + 10**10))  # (a later edit, whatever the clock's step)
    edited = _force(copy, tmp_path / "cache")
    cold = _force(copy, tmp_path / "cold")
    assert cold != before  # the edit changes the inverse's force
    assert edited == cold, f"the cached inverse kept the rule before the edit: {edited} (before {before}, edited {cold})"


def _imported_modules(path: Path) -> set[str]:
    """The cellbridge.tactile modules ``path`` imports anything from."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            if node.module == "cellbridge.tactile":
                out |= {a.name for a in node.names}
            elif node.module.startswith("cellbridge.tactile."):
                out.add(node.module.rsplit(".", 1)[1])
    return out - {"_jit"}


def test_the_sources_a_kernel_cache_is_checked_against_hold_every_module_a_kernel_module_imports_from() -> None:
    todo = [p.stem for p in TACTILE.glob("*.py") if "_jit import compiled" in p.read_text() and p.stem != "_jit"]
    assert todo
    need: set[str] = set()
    while todo:  # (the modules kernel modules import from, and theirs: their code may be compiled in)
        name = todo.pop()
        if name not in need:
            need.add(name)
            todo += [m for m in _imported_modules(TACTILE / f"{name}.py") if (TACTILE / f"{m}.py").exists()]
    assert need <= set(_jit.KERNEL_SOURCES), sorted(need - set(_jit.KERNEL_SOURCES))
