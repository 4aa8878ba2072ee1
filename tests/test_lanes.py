"""The suite's two lanes: `process` marks every test that starts a process or a pty
(tests/conftest.py), `make test-fast` runs the others; the guard fails a test that starts
one without the mark."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import conftest

ROOT = Path(__file__).resolve().parent.parent


def test_an_unmarked_test_that_opens_a_pty_or_starts_a_process_is_caught(request: pytest.FixtureRequest) -> None:
    a, b = os.openpty()
    os.close(a)
    os.close(b)
    subprocess.run([sys.executable, "-c", "pass"], check=True)
    # (taken back here, or this test would fail at its teardown as the guard says)
    caught = conftest._started.pop(request.node.nodeid, [])
    assert "os.openpty" in caught and "fork_exec" in caught


@pytest.mark.process
def test_a_marked_test_may_start_processes(request: pytest.FixtureRequest) -> None:
    subprocess.run([sys.executable, "-c", "pass"], check=True)
    assert request.node.nodeid not in conftest._started


def test_the_process_modules_exist_and_mark_their_tests(request: pytest.FixtureRequest) -> None:
    have = {p.stem for p in (ROOT / "tests").glob("test_*.py")}
    assert conftest.PROCESS_MODULES <= have, sorted(conftest.PROCESS_MODULES - have)
    for item in request.session.items:
        module = getattr(item, "module", None)
        name = module.__name__.rpartition(".")[2] if module is not None else ""
        if name in conftest.PROCESS_MODULES:
            assert item.get_closest_marker("process") is not None, item.nodeid
    assert request.node.get_closest_marker("process") is None


def test_make_has_a_fast_lane_and_the_markers_are_registered() -> None:
    make = (ROOT / "Makefile").read_text()
    assert '-m "not process and not slow"' in make and "test-fast:" in make
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert '"process: ' in pyproject and '"slow: ' in pyproject


def test_the_slow_lists_name_tests_that_exist() -> None:
    """A renamed or removed test left in SLOW_TESTS would silently put its successor back in
    the quick lane (and a module in SLOW_MODULES the same): every name must match a test."""
    tests = ROOT / "tests"
    modules = {p.stem for p in tests.glob("test_*.py")}
    assert conftest.SLOW_MODULES <= modules, sorted(conftest.SLOW_MODULES - modules)
    for entry in conftest.SLOW_TESTS:
        module, _, name = entry.partition("::")
        assert module in modules, entry
        assert f"def {name}(" in (tests / f"{module}.py").read_text(), entry


def _imported(path: Path) -> list[str]:
    """Every module name ``path`` imports (lazy imports inside functions too, and the
    ``-c`` scripts it writes out are not seen: those are checked by running them)."""
    import ast

    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    names += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.level == 0]
    return names


def _sources(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def test_no_test_file_or_bench_script_imports_a_test_file() -> None:
    """What tests and benchmarks share lives in helper modules: importing a test file runs
    (and, under pytest, collects) its tests' module too, and couples two files' fixtures."""
    found = [f"{p.relative_to(ROOT)} imports {n}" for d in ("tests", "bench") for p in _sources(d)
             for n in _imported(p) if n.split(".")[0].startswith("test_")]
    assert not found, found


def test_the_tests_helpers_live_in_tests_support() -> None:
    """``tests/`` holds test files and conftest.py; every other module of the tests is in the
    ``support`` package beside them, so a reader tells a test from a helper by where it is."""
    loose = [p.name for p in (ROOT / "tests").glob("*.py") if p.name != "conftest.py" and not p.name.startswith("test_")]
    assert not loose, f"helpers outside tests/support: {loose}"
    assert (ROOT / "tests" / "support" / "__init__.py").is_file()
    tests_in_support = [p.name for p in (ROOT / "tests" / "support").rglob("test_*.py")]
    assert not tests_in_support, tests_in_support


def test_benchmarks_import_nothing_from_tests() -> None:
    """A benchmark runs against the package (and, through bench/timing.py, against another
    revision's): the rigs it shares with the tests live in bench/, never in tests/."""
    from_tests = {"support", "conftest"} | {p.stem for p in (ROOT / "tests").glob("*.py")}
    found = [f"{p.relative_to(ROOT)} imports {n}" for p in _sources("bench") for n in _imported(p)
             if n.split(".")[0] in from_tests]
    found += [f"{p.relative_to(ROOT)} puts tests/ on its path" for p in _sources("bench")
              if '"tests"' in p.read_text(encoding="utf-8")]
    assert not found, found


def test_a_module_of_the_tests_imports_helpers_from_support_or_bench() -> None:
    """A test's import names a helper where it lives (``support.x``, or a rig of bench/), not a
    bare name that happens to resolve through some folder on the path."""
    rigs = {p.stem for p in (ROOT / "bench").glob("*.py")}
    helpers = {p.stem for p in (ROOT / "tests" / "support").glob("*.py")} - {"__init__"}
    bare = [f"{p.relative_to(ROOT)} imports {n}" for p in _sources("tests") for n in _imported(p)
            if n.split(".")[0] in helpers and n.split(".")[0] not in rigs]
    assert not bare, bare
