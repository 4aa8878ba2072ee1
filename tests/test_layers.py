"""The layers' import rules, and the cores and shells of the daemon (docs/daemon.md) and the
emulator (docs/emulator.md), both under "Cores and shells", checked on the source by path:
the docs say which sub-packages are cores, and every module under one is held to a core's rules.

Every ``import`` of every module of a layer folder is read from its syntax tree, those
inside functions included (a lazy import is still a dependency), and held against what
the layer may import: the other layers of the package and the libraries outside the
standard library. The protocol layer is also kept free of I/O and clocks.
"""

from __future__ import annotations

import ast
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: layer folder -> (cellbridge sub-packages it may import, third-party libraries it may import)
RULES: dict[str, tuple[set[str], set[str]]] = {
    "protocol": ({"protocol"}, {"msgpack", "cobs"}),
    "tactile": ({"tactile"}, {"numpy", "numba"}),  # numba: compiled kernels of the same numpy code
    # mujoco: a simulated robot as the skin's world (emulator/world/robot_world.py, the robot extra)
    "emulator": ({"emulator", "protocol", "tactile"}, {"numpy", "msgpack", "zmq", "setproctitle", "mujoco"}),
    # mcap: the daemon takes a recording's serial channel as a link (``replay:FILE.mcap``);
    # yourdfpy: a skin description's link frames from the robot's URDF (the robot extra)
    # zstandard, lz4: an MCAP recording's chunks, decompressed within bounds (daemon/core/mcap_chunks.py)
    "daemon": ({"daemon", "protocol", "tactile"}, {"numpy", "msgpack", "zmq", "serial", "mcap", "yourdfpy",
                                                  "zstandard", "lz4"}),
}
#: The modules of the top package any layer may read: leaves without imports (version, root error).
SHARED = {"_version", "errors"}
#: Standard-library modules that would put I/O, event loops or clocks into the pure protocol layer.
IMPURE = {"asyncio", "socket", "selectors", "select", "serial", "threading", "time", "os", "subprocess", "io"}


def imports(path: Path, root: Path) -> list[tuple[int, str]]:
    """(line, absolute name) of every import in ``path`` (a module of the layer folders
    under ``root``); relative ones resolved, ``from m import x`` as ``m.x``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    package = ".".join(("cellbridge", *path.relative_to(root).parts[:-1]))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
            name = (f"{base}.{node.module}" if node.module else base) if node.level else node.module or ""
            # each name taken as ``module.name``: ``from cellbridge.emulator import udp`` imports
            # the module udp (a name that is a class or function only lengthens the path)
            out += [(node.lineno, f"{name}.{a.name}" if name and a.name != "*" else name) for a in node.names]
    return out


def violations(root: Path) -> list[str]:
    """Every import in the layer folders under ``root`` that its layer's rules forbid."""
    found = []
    for layer, (layers, libraries) in RULES.items():
        for path in sorted((root / layer).rglob("*.py")):
            where = path.relative_to(root)
            for line, name in imports(path, root):
                top, _, rest = name.partition(".")
                if top == "cellbridge":
                    sub = rest.split(".")[0]
                    if not rest or (sub not in layers and sub not in SHARED):
                        found.append(f"{where}:{line}: {layer}/ imports {name} (may import {sorted(layers)})")
                elif top in sys.stdlib_module_names or top == "__future__":
                    if layer == "protocol" and top in IMPURE:
                        found.append(f"{where}:{line}: protocol/ imports {name}: no I/O, asyncio or clocks")
                elif top not in libraries:
                    found.append(f"{where}:{line}: {layer}/ imports {name} (libraries: {sorted(libraries)})")
    return found


def test_every_layer_imports_only_what_the_design_allows() -> None:
    found = violations(ROOT)
    assert not found, "\n".join(found)


def test_the_check_catches_a_daemon_importing_the_emulator_and_a_protocol_importing_asyncio(
        tmp_path: Path) -> None:
    for layer in RULES:
        (tmp_path / layer).mkdir()
    (tmp_path / "daemon" / "bad.py").write_text("def f():\n    from cellbridge.emulator import virtual\n")
    (tmp_path / "protocol" / "bad.py").write_text("import asyncio\nfrom . import frame\n")
    (tmp_path / "emulator" / "bad.py").write_text("from cellbridge import __version__\nfrom ..daemon import x\n")
    (tmp_path / "tactile" / "bad.py").write_text("import zmq\n")
    got = violations(tmp_path)
    assert len(got) == 5, got
    assert any(v.startswith("daemon/bad.py:2: daemon/ imports cellbridge.emulator") for v in got)
    assert any(v.startswith("protocol/bad.py:1: protocol/ imports asyncio") for v in got)
    assert any("emulator/ imports cellbridge.__version__" in v for v in got)
    assert any("emulator/ imports cellbridge.daemon.x " in v for v in got)
    assert any("tactile/ imports zmq" in v for v in got)


# -- cores and shells by path (docs/daemon.md and docs/emulator.md, "Cores and shells") ---------

#: What a module of a core package may not import: event loops, sockets, devices, threads,
#: processes, signals, clocks and loggers (a core is fed the time and returns its log events).
CORE_FORBIDDEN = {"asyncio", "socket", "selectors", "select", "signal", "threading", "multiprocessing",
                  "concurrent", "subprocess", "time", "logging", "zmq", "serial", "mcap"}


def layer_tables(doc: Path) -> tuple[dict[str, str], set[str]]:
    """From the tables under ``## Cores and shells`` in ``doc``: {package: "core" | "shell"}
    (the rows naming ``pkg/``) and the modules named ``pkg/module``."""
    kinds: dict[str, str] = {}
    modules: set[str] = set()
    inside = False
    for line in doc.read_text(encoding="utf-8").splitlines():
        if line.startswith("## "):
            inside = line.strip() == "## Cores and shells"
        elif inside and line.startswith("| `"):
            cells = [c.strip() for c in line.split("|")[1:-1]]
            name = cells[0].strip("`")
            if name.endswith("/"):
                kinds[name.rstrip("/")] = cells[1]
            else:
                modules.add(name)
    return kinds, modules


def core_violations(root: Path, doc: Path, layer: str = "daemon") -> list[str]:
    """Every import that a module of a core package of ``layer`` (``doc``'s first table says
    which) may not make: I/O, or any module of a shell package; the layer's own
    ``__init__.py``, which importing any of its modules runs, is held to a core's rules too.
    Also every package the table does not list (held to a core's rules all the same), every
    row naming no package, no module or an unknown kind, every module outside a package and
    every module the second table does not name."""
    kinds, named = layer_tables(doc)
    base = root / layer
    packages = {p.parent.name for p in base.glob("*/__init__.py")}
    found = [f"{doc.name}: `{p}/` is listed but {layer}/{p}/ is not a package" for p in sorted(set(kinds) - packages)]
    found += [f"{doc.name}: `{p}/` is a {k!r}, not a core or a shell" for p, k in sorted(kinds.items())
              if k not in ("core", "shell")]
    found += [f"{layer}/{p}/: a package {doc.name} does not list" for p in sorted(packages - set(kinds))]
    found += [f"{layer}/{p.name}: a module outside the packages of {doc.name}" for p in sorted(base.glob("*.py"))
              if p.name != "__init__.py"]
    modules = {p.relative_to(base).with_suffix("").as_posix() for p in base.glob("*/**/*.py")
               if p.name != "__init__.py"}
    found += [f"{doc.name}: `{m}` is named but {layer}/{m}.py does not exist" for m in sorted(named - modules)]
    found += [f"{layer}/{m}.py: a module {doc.name} does not name" for m in sorted(modules - named)]
    shells = {p for p, k in kinds.items() if k == "shell"}
    cores = [base / "__init__.py", *(path for p in sorted(packages - shells) for path in sorted((base / p).rglob("*.py")))]
    for path in cores:
        if not path.exists():
            continue
        where = path.relative_to(root).as_posix()
        for line, name in imports(path, root):
            top, _, rest = name.partition(".")
            parts = rest.split(".")
            if top in CORE_FORBIDDEN:
                found.append(f"{where}:{line}: the core imports {name} (I/O belongs in a shell)")
            elif top == "cellbridge" and parts[0] == layer and len(parts) > 1 and parts[1] in shells:
                found.append(f"{where}:{line}: the core imports the shell {name}")
    return found


def test_daemon_cores_do_no_io_and_import_no_shell() -> None:
    kinds, _ = layer_tables(ROOT / "docs" / "daemon.md")
    assert kinds == {"core": "core", "shell": "shell", "ops": "shell"}, kinds
    found = core_violations(ROOT, ROOT / "docs" / "daemon.md")
    assert not found, "\n".join(found)


def test_the_core_check_catches_io_in_a_core_and_a_core_reaching_a_shell(tmp_path: Path) -> None:
    (tmp_path / "daemon").mkdir()
    for package in ("core", "shell", "odd", "late"):
        (tmp_path / "daemon" / package).mkdir()
        (tmp_path / "daemon" / package / "__init__.py").write_text("")
    doc = tmp_path / "daemon.md"
    doc.write_text("## Cores and shells\n\n| package | kind | what |\n|---|---|---|\n"
                   "| `core/` | core | x |\n| `shell/` | shell | y |\n| `gone/` | core | z |\n"
                   "| `odd/` | both | w |\n\n| module | what |\n|---|---|\n| `core/pipeline` | p |\n"
                   "| `shell/service` | s |\n| `core/lost` | l |\n| `late/late` | t |\n"
                   "\n## Next\n| `late/` | shell | not this table |\n")
    (tmp_path / "daemon" / "core" / "pipeline.py").write_text(
        "import time\nfrom cellbridge.daemon.shell.service import Service\nfrom cellbridge.daemon import shell\n")
    (tmp_path / "daemon" / "shell" / "service.py").write_text("import asyncio\nimport zmq\n")  # a shell may
    (tmp_path / "daemon" / "shell" / "extra.py").write_text("")
    (tmp_path / "daemon" / "late" / "late.py").write_text("def f():\n    import zmq.asyncio\n")  # unlisted: a core
    (tmp_path / "daemon" / "loose.py").write_text("")
    (tmp_path / "daemon" / "__init__.py").write_text("import logging\n")  # runs on every import of a core
    got = core_violations(tmp_path, doc)
    assert sorted(got) == sorted([
        "daemon.md: `gone/` is listed but daemon/gone/ is not a package",
        "daemon.md: `odd/` is a 'both', not a core or a shell",
        "daemon/late/: a package daemon.md does not list",
        "daemon/loose.py: a module outside the packages of daemon.md",
        "daemon.md: `core/lost` is named but daemon/core/lost.py does not exist",
        "daemon/shell/extra.py: a module daemon.md does not name",
        "daemon/__init__.py:1: the core imports logging (I/O belongs in a shell)",
        "daemon/core/pipeline.py:1: the core imports time (I/O belongs in a shell)",
        "daemon/core/pipeline.py:2: the core imports the shell cellbridge.daemon.shell.service.Service",
        "daemon/core/pipeline.py:3: the core imports the shell cellbridge.daemon.shell",
        "daemon/late/late.py:2: the core imports zmq.asyncio (I/O belongs in a shell)",
    ]), got


def test_emulator_cores_do_no_io_and_import_no_shell() -> None:
    """The firmware, the chip and the medium run the same in the real-time processes, the
    virtual-time mesh and the tests: only the process shells touch sockets and clocks."""
    kinds, _ = layer_tables(ROOT / "docs" / "emulator.md")
    assert kinds == {"chip": "core", "firmware": "core", "medium": "core", "world": "core", "mesh": "core",
                     "realtime": "shell"}, kinds
    found = core_violations(ROOT, ROOT / "docs" / "emulator.md", "emulator")
    assert not found, "\n".join(found)


def test_the_emulator_check_catches_a_firmware_opening_a_socket(tmp_path: Path) -> None:
    for package in ("firmware", "realtime"):
        (tmp_path / "emulator" / package).mkdir(parents=True)
        (tmp_path / "emulator" / package / "__init__.py").write_text("")
    doc = tmp_path / "emulator.md"
    doc.write_text("## Cores and shells\n\n| package | kind | what |\n|---|---|---|\n"
                   "| `firmware/` | core | x |\n| `realtime/` | shell | y |\n\n| module | what |\n|---|---|\n"
                   "| `firmware/firmware` | f |\n| `realtime/udp` | u |\n")
    (tmp_path / "emulator" / "firmware" / "firmware.py").write_text(
        "import socket\nfrom cellbridge.emulator.realtime import udp\nfrom ..realtime.udp import x\n")
    (tmp_path / "emulator" / "realtime" / "udp.py").write_text("import socket\n")  # a shell may
    got = core_violations(tmp_path, doc, "emulator")
    assert got == ["emulator/firmware/firmware.py:1: the core imports socket (I/O belongs in a shell)",
                   "emulator/firmware/firmware.py:2: the core imports the shell cellbridge.emulator.realtime.udp",
                   "emulator/firmware/firmware.py:3: the core imports the shell cellbridge.emulator.realtime.udp.x"], got


# -- no reach-ins: an owner's state is read and changed through its methods -------------------

#: ``owner.attribute`` pairs (as written: the attribute a module holds the owner in, then what it
#: touches) that reach into another object, each with the module that owns it (its path under
#: daemon/, the only one that may) and the method the others call instead.
REACH_INS = {
    ("dedupe", "window"): ("core/wire", "Ingress.dedupe_window()"),
    ("dedupe", "duplicates"): ("core/wire", "Ingress.totals()"),
    ("reassembler", "expire"): ("core/wire", "Ingress.expire()"),
    ("ingress", "reassembly_drops"): ("core/wire", "Ingress.drops_of() / Ingress.forget()"),
    ("nodes", "pop"): ("core/topology", "Topology.forget()"),
    ("elements", "held_for"): ("core/elements", "ElementStage.hold_for()"),
    ("elements", "stepped"): ("core/elements", "what ElementStage.step() / flush() return"),
    ("elements", "touched"): ("core/elements", "what ElementStage.step() / flush() return, ElementStage.touched_rows()"),
    ("elements", "calibrator"): ("core/elements", "ElementStage.thresholds() / calibration_health() / not_ready_rows()"),
    ("host", "pipeline"): ("shell/service", "the control server's Host methods"),
    ("host", "links"): ("shell/service", "Host.send_command(): the service writes on its links"),
    ("clock", "bridges"): ("core/clock", "HostTimes' own methods"),
}
#: Attributes only their own module may touch.
PRIVATE_TO = {"_samples_at_tick": "core/health"}


def reach_ins(root: Path) -> list[str]:
    """Every ``x.owner.attribute`` of :data:`REACH_INS` outside its owner's module, and every
    attribute of :data:`PRIVATE_TO` touched outside its module, in the daemon's modules."""
    found = []
    for path in sorted((root / "daemon").rglob("*.py")):
        module = path.relative_to(root / "daemon").with_suffix("").as_posix()
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for node in sorted((n for n in ast.walk(tree) if isinstance(n, ast.Attribute)),
                           key=lambda n: (n.lineno, n.col_offset)):
            pair = (node.value.attr, node.attr) if isinstance(node.value, ast.Attribute) else None
            if pair in REACH_INS and REACH_INS[pair][0] != module:
                found.append(f"daemon/{module}.py:{node.lineno}: reaches into {'.'.join(pair)} "
                             f"(use {REACH_INS[pair][1]})")
            owner = PRIVATE_TO.get(node.attr)
            if owner is not None and module != owner:
                found.append(f"daemon/{module}.py:{node.lineno}: touches {node.attr}, private to daemon/{owner}.py")
    return found


def test_no_daemon_module_reaches_into_another_owners_attributes() -> None:
    owners = {owner for owner, _ in REACH_INS.values()} | set(PRIVATE_TO.values())
    missing = sorted(o for o in owners if not (ROOT / "daemon" / f"{o}.py").exists())
    assert not missing, f"owners that are no module (the rule would never fire): {missing}"
    found = reach_ins(ROOT)
    assert not found, "\n".join(found)


def test_the_reach_in_check_catches_each_kind(tmp_path: Path) -> None:
    for package in ("core", "shell"):
        (tmp_path / "daemon" / package).mkdir(parents=True)
    (tmp_path / "daemon" / "core" / "pipeline.py").write_text(
        "def f(self, b):\n    w = self.ingress.dedupe.window\n    self.topology.nodes.pop(1, None)\n"
        "    b._samples_at_tick = 0\n    self.host.links['a'].write(b'')\n")
    (tmp_path / "daemon" / "core" / "health.py").write_text("def g(b):\n    b._samples_at_tick = 0\n")  # its own
    (tmp_path / "daemon" / "core" / "topology.py").write_text("def h(self):\n    self.nodes.pop(1, None)\n")  # its own
    (tmp_path / "daemon" / "shell" / "health.py").write_text("def g(b):\n    b._samples_at_tick = 0\n")  # not the owner
    got = reach_ins(tmp_path)
    assert got == ["daemon/core/pipeline.py:2: reaches into dedupe.window (use Ingress.dedupe_window())",
                   "daemon/core/pipeline.py:3: reaches into nodes.pop (use Topology.forget())",
                   "daemon/core/pipeline.py:4: touches _samples_at_tick, private to daemon/core/health.py",
                   "daemon/core/pipeline.py:5: reaches into host.links (use Host.send_command(): the service "
                   "writes on its links)",
                   "daemon/shell/health.py:2: touches _samples_at_tick, private to daemon/core/health.py"], got


# -- the installed distribution carries every package ----------------------------------------

def source_packages(root: Path) -> set[str]:
    """The dotted name of every package (a folder with ``__init__.py``) of the top package
    and the layer folders under ``root``, as installed (``daemon/core`` is ``cellbridge.daemon.core``)."""
    found = set()
    for top, name in [("cellbridge", "cellbridge"), *((layer, f"cellbridge.{layer}") for layer in RULES)]:
        for init in (root / top).rglob("__init__.py"):
            parts = init.parent.relative_to(root / top).parts
            found.add(".".join((name, *parts)))
    return found


def test_pyproject_lists_every_package_so_a_non_editable_install_carries_it() -> None:
    """pyproject names its packages one by one (the layer folders map into cellbridge): a
    sub-package it does not name is left out of a wheel, though the editable install and
    every test here would still import it from the checkout."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    listed = set(config["tool"]["setuptools"]["packages"])
    found = source_packages(ROOT)
    assert found == listed, f"not in pyproject: {sorted(found - listed)}; no such package: {sorted(listed - found)}"


# -- docs, units and docstrings name modules that exist -----------------------------------------

#: Where the daemon's and the emulator's dotted names are written for readers: the docs, the
#: README, the systemd units, the benchmarks and the package sources' docstrings (tests/ is
#: left out: its layer checks name made-up modules on purpose).
NAMED_IN = ("docs", "README.md", "systemd", "bench", "cellbridge", *RULES)
DOTTED = r"cellbridge\.(?:daemon|emulator)(?:\.[A-Za-z_][A-Za-z0-9_]*)+"


def unresolved_names(root: Path) -> list[str]:
    """``file:line: name`` of every ``cellbridge.daemon.*``/``cellbridge.emulator.*`` dotted
    name under ``root`` that is neither a module nor an attribute of one."""
    import importlib
    import re

    def resolves(name: str) -> bool:
        parts = name.split(".")
        for i in range(len(parts), 1, -1):
            try:
                obj: object = importlib.import_module(".".join(parts[:i]))
            except ModuleNotFoundError:
                continue
            for attr in parts[i:]:
                if not hasattr(obj, attr):
                    return False
                obj = getattr(obj, attr)
            return True
        return False

    out = []
    for where in NAMED_IN:
        path = root / where
        files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file()
                                                     and p.suffix in (".py", ".md", ".service", ".toml", ".txt"))
        for f in files:
            for n, line in enumerate(f.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
                for name in re.findall(DOTTED, line):
                    if not resolves(name):
                        out.append(f"{f.relative_to(root)}:{n}: {name}")
    return out


def test_every_daemon_and_emulator_name_in_docs_units_and_docstrings_resolves() -> None:
    """The sub-packages moved modules (``daemon/service.py`` to ``daemon/shell/service.py``):
    a doc, a unit or a docstring still naming the old place sends its reader nowhere."""
    assert not unresolved_names(ROOT)
