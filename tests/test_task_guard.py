"""The guard of tests/conftest.py that fails a test whose event loop closes with tasks still
pending: through ``asyncio.run``, a loop closed by hand, a loop in another thread; and a
test that cancels and awaits what it started passes."""

from __future__ import annotations

import asyncio
import subprocess
import sys
import threading
from pathlib import Path

import pytest

import conftest

TESTS = Path(__file__).resolve().parent


async def _forgotten() -> None:
    await asyncio.sleep(3600)


def _taken_back(request: pytest.FixtureRequest) -> list[str]:
    # (taken back here, or this test would fail at its teardown as the guard says)
    return conftest._leaked.pop(request.node.nodeid, [])


def test_a_task_left_pending_when_asyncio_run_returns_is_caught(request: pytest.FixtureRequest) -> None:
    async def main() -> None:
        asyncio.create_task(_forgotten(), name="reader")
        await asyncio.sleep(0)  # it starts, and waits

    asyncio.run(main())
    (caught,) = _taken_back(request)
    assert caught.startswith("reader (_forgotten at ") and __file__ in caught, caught


def test_a_task_on_a_loop_closed_by_hand_is_caught(request: pytest.FixtureRequest) -> None:
    loop = asyncio.new_event_loop()
    task = loop.create_task(_forgotten(), name="timer")
    loop.run_until_complete(asyncio.sleep(0))
    loop.close()
    assert not task.done()
    assert [c.split(" ")[0] for c in _taken_back(request)] == ["timer"]


def test_a_task_on_another_threads_loop_is_caught(request: pytest.FixtureRequest) -> None:
    async def main() -> None:
        asyncio.create_task(_forgotten(), name="in-thread")
        await asyncio.sleep(0)

    thread = threading.Thread(target=asyncio.run, args=(main(),))
    thread.start()
    thread.join(30)
    assert [c.split(" ")[0] for c in _taken_back(request)] == ["in-thread"]


def test_tasks_cancelled_and_awaited_before_the_loop_ends_pass(request: pytest.FixtureRequest) -> None:
    async def main() -> None:
        tasks = [asyncio.create_task(_forgotten()) for _ in range(3)]
        done = asyncio.create_task(asyncio.sleep(0))
        await done
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    asyncio.run(main())
    assert request.node.nodeid not in conftest._leaked


@pytest.mark.process
def test_the_guard_fails_the_test_that_leaks_and_names_the_task(tmp_path: Path) -> None:
    """End to end: a pytest run of a leaking test and a clean one, with this suite's conftest."""
    (tmp_path / "conftest.py").write_text((TESTS / "conftest.py").read_text())
    (tmp_path / "test_leaky.py").write_text(
        "import asyncio\n\n"
        "async def forever():\n    await asyncio.sleep(3600)\n\n"
        "def test_leaks():\n"
        "    async def main():\n        asyncio.create_task(forever(), name='orphan')\n        await asyncio.sleep(0)\n"
        "    asyncio.run(main())\n\n"
        "def test_clean():\n    asyncio.run(asyncio.sleep(0))\n")
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                          "-o", "addopts=", "-n", "0", str(tmp_path)], cwd=tmp_path, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 1, run.stdout[-3000:] + run.stderr[-3000:]
    assert "2 passed, 1 error" in run.stdout  # test_leaks: its call passes, its teardown fails, run.stdout[-3000:]
    assert "ERROR at teardown of test_leaks" in run.stdout and "orphan (forever at " in run.stdout, run.stdout[-3000:]
