"""What the tests share and is not a test: fixtures' machinery, strategies, vectors, fakes.

A test imports a helper as ``from support.x import y`` (``tests/`` is on the tests'
``sys.path``). The rigs the benchmarks use too (a daemon on a pty, synthesized gateway
traffic, a live skin, the views' clients, ...) live in ``bench/``, which is on the tests'
path as well: a benchmark never imports from ``tests/``. tests/test_lanes.py keeps that so.
"""
