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
        name = item.module.__name__.rpartition(".")[2] if getattr(item, "module", None) is not None else ""
        if name in conftest.PROCESS_MODULES:
            assert item.get_closest_marker("process") is not None, item.nodeid
    assert request.node.get_closest_marker("process") is None


def test_make_has_a_fast_lane_and_the_marker_is_registered() -> None:
    make = (ROOT / "Makefile").read_text()
    assert '-m "not process"' in make and "test-fast:" in make
    assert '"process: ' in (ROOT / "pyproject.toml").read_text()


def _imported_test_modules(path: Path) -> list[str]:
    import ast

    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    names += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    return [n for n in names if n.split(".")[0].startswith("test_")]


def test_no_test_file_or_bench_script_imports_a_test_file() -> None:
    """What tests and benchmarks share lives in helper modules: importing a test file runs
    (and, under pytest, collects) its tests' module too, and couples two files' fixtures."""
    found = [f"{p.relative_to(ROOT)} imports {n}" for d in ("tests", "bench") for p in sorted((ROOT / d).glob("*.py"))
             for n in _imported_test_modules(p)]
    assert not found, found
