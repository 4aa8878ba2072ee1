"""The layers' import rules, and the cores and shells of the daemon (docs/daemon.md) and the
emulator (docs/emulator.md), both under "Cores and shells", checked on the source.

Every ``import`` of every module of a layer folder is read from its syntax tree, those
inside functions included (a lazy import is still a dependency), and held against what
the layer may import: the other layers of the package and the libraries outside the
standard library. The protocol layer is also kept free of I/O and clocks.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

#: layer folder -> (cellbridge sub-packages it may import, third-party libraries it may import)
RULES: dict[str, tuple[set[str], set[str]]] = {
    "protocol": ({"protocol"}, {"msgpack", "cobs"}),
    "tactile": ({"tactile"}, {"numpy", "numba"}),  # numba: compiled kernels of the same numpy code
    # mujoco: a simulated robot as the skin's world (emulator/robot_world.py, the robot extra)
    "emulator": ({"emulator", "protocol", "tactile"}, {"numpy", "msgpack", "zmq", "setproctitle", "mujoco"}),
    # mcap: the daemon takes a recording's serial channel as a link (``replay:FILE.mcap``);
    # yourdfpy: a skin description's link frames from the robot's URDF (the robot extra)
    # zstandard, lz4: an MCAP recording's chunks, decompressed within bounds (daemon/mcap_chunks.py)
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


# -- the daemon's cores and shells (docs/daemon.md, "Cores and shells") -----------------------

#: What a daemon core may not import: event loops, sockets, devices, threads, processes,
#: signals, clocks and loggers (a core is fed the time and returns its log events).
CORE_FORBIDDEN = {"asyncio", "socket", "selectors", "select", "signal", "threading", "multiprocessing",
                  "concurrent", "subprocess", "time", "logging", "zmq", "serial", "mcap"}


def layer_kinds(doc: Path) -> dict[str, str]:
    """{module: "core" | "shell"} from the table under ``## Cores and shells`` in ``doc``."""
    kinds: dict[str, str] = {}
    inside = False
    for line in doc.read_text(encoding="utf-8").splitlines():
        if line.startswith("## "):
            inside = line.strip() == "## Cores and shells"
        elif inside and line.startswith("| `"):
            cells = [c.strip() for c in line.split("|")[1:-1]]
            kinds[cells[0].strip("`")] = cells[1]
    return kinds


def core_violations(root: Path, doc: Path, layer: str = "daemon") -> list[str]:
    """Every import of a core of ``layer`` (a module ``doc``'s table does not call a shell)
    that a core may not make, and every table row naming no module or an unknown kind."""
    kinds = layer_kinds(doc)
    modules = {p.stem for p in (root / layer).glob("*.py")} - {"__init__"}
    found = [f"{doc.name}: `{m}` is listed but {layer}/{m}.py does not exist" for m in sorted(set(kinds) - modules)]
    found += [f"{doc.name}: `{m}` is a {k!r}, not a core or a shell" for m, k in sorted(kinds.items())
              if k not in ("core", "shell")]
    shells = {m for m, k in kinds.items() if k == "shell"}
    for module in sorted(modules - shells):
        path = root / layer / f"{module}.py"
        for line, name in imports(path, root):
            top, _, rest = name.partition(".")
            if top in CORE_FORBIDDEN:
                found.append(f"{layer}/{module}.py:{line}: the core imports {name} (I/O belongs in a shell)")
            elif top == "cellbridge" and rest.startswith(f"{layer}.") and rest.split(".")[1] in shells:
                found.append(f"{layer}/{module}.py:{line}: the core imports the shell {name}")
    return found


def test_daemon_cores_do_no_io_and_import_no_shell() -> None:
    kinds = layer_kinds(ROOT / "docs" / "daemon.md")
    assert {"pipeline", "wire", "clock"} <= {m for m, k in kinds.items() if k == "core"}
    assert {"service", "links", "publisher", "control_server", "notify"} <= {m for m, k in kinds.items()
                                                                           if k == "shell"}
    found = core_violations(ROOT, ROOT / "docs" / "daemon.md")
    assert not found, "\n".join(found)


def test_the_core_check_catches_io_in_a_core_and_a_core_reaching_a_shell(tmp_path: Path) -> None:
    (tmp_path / "daemon").mkdir()
    doc = tmp_path / "daemon.md"
    doc.write_text("## Cores and shells\n\n| module | kind | what |\n|---|---|---|\n"
                   "| `pipeline` | core | x |\n| `service` | shell | y |\n| `gone` | core | z |\n"
                   "| `odd` | both | w |\n\n## Next\n| `late` | shell | not this table |\n")
    (tmp_path / "daemon" / "pipeline.py").write_text("import time\nfrom cellbridge.daemon.service import Service\n")
    (tmp_path / "daemon" / "service.py").write_text("import asyncio\nimport zmq\n")  # a shell may
    (tmp_path / "daemon" / "odd.py").write_text("")
    (tmp_path / "daemon" / "late.py").write_text("def f():\n    import zmq.asyncio\n")  # unlisted: a core
    got = core_violations(tmp_path, doc)
    assert len(got) == 5, got
    assert "daemon/pipeline.py:1: the core imports time (I/O belongs in a shell)" in got
    assert "daemon/pipeline.py:2: the core imports the shell cellbridge.daemon.service.Service" in got
    assert "daemon/late.py:2: the core imports zmq.asyncio (I/O belongs in a shell)" in got
    assert any("`gone` is listed" in v for v in got) and any("`odd` is a 'both'" in v for v in got)


def test_emulator_cores_do_no_io_and_import_no_shell() -> None:
    """The firmware, the chip and the medium run the same in the real-time processes, the
    virtual-time mesh and the tests: only the process shells touch sockets and clocks."""
    kinds = layer_kinds(ROOT / "docs" / "emulator.md")
    assert {"firmware", "chip", "medium", "readout", "virtual"} <= {m for m, k in kinds.items() if k == "core"}
    assert {"process_bridge", "process_medium", "udp", "gateway_port"} <= {m for m, k in kinds.items()
                                                                         if k == "shell"}
    found = core_violations(ROOT, ROOT / "docs" / "emulator.md", "emulator")
    assert not found, "\n".join(found)


def test_every_emulator_module_is_in_its_table() -> None:
    """A new module is said to be a core or a shell where the others are (unlisted, it is
    held to a core's rules; listed, a reader sees the layer at a glance)."""
    listed = set(layer_kinds(ROOT / "docs" / "emulator.md"))
    modules = {p.stem for p in (ROOT / "emulator").glob("*.py")} - {"__init__"}
    assert modules == listed, f"not listed: {sorted(modules - listed)}; listed, no module: {sorted(listed - modules)}"


def test_the_emulator_check_catches_a_firmware_opening_a_socket(tmp_path: Path) -> None:
    (tmp_path / "emulator").mkdir()
    doc = tmp_path / "emulator.md"
    doc.write_text("## Cores and shells\n\n| module | kind | what |\n|---|---|---|\n"
                   "| `firmware` | core | x |\n| `udp` | shell | y |\n")
    (tmp_path / "emulator" / "firmware.py").write_text("import socket\nfrom cellbridge.emulator import udp\n")
    (tmp_path / "emulator" / "udp.py").write_text("import socket\n")  # a shell may
    got = core_violations(tmp_path, doc, "emulator")
    assert got == ["emulator/firmware.py:1: the core imports socket (I/O belongs in a shell)",
                   "emulator/firmware.py:2: the core imports the shell cellbridge.emulator.udp"], got


# -- no reach-ins: an owner's state is read and changed through its methods -------------------

#: ``owner.attribute`` pairs (as written: the attribute a module holds the owner in, then what it
#: touches) that reach into another object, each with the module that owns it (the only one
#: that may) and the method the others call instead.
REACH_INS = {
    ("dedupe", "window"): ("wire", "Ingress.dedupe_window()"),
    ("dedupe", "duplicates"): ("wire", "Ingress.totals()"),
    ("reassembler", "expire"): ("wire", "Ingress.expire()"),
    ("ingress", "reassembly_drops"): ("wire", "Ingress.drops_of() / Ingress.forget()"),
    ("nodes", "pop"): ("topology", "Topology.forget()"),
    ("elements", "held_for"): ("elements", "ElementStage.hold_for()"),
    ("elements", "stepped"): ("elements", "what ElementStage.step() / flush() return"),
    ("elements", "touched"): ("elements", "what ElementStage.step() / flush() return, ElementStage.touched_rows()"),
    ("elements", "calibrator"): ("elements", "ElementStage.thresholds() / calibration_health() / not_ready_rows()"),
    ("host", "pipeline"): ("service", "the control server's Host methods"),
    ("host", "links"): ("service", "Host.send_command(): the service writes on its links"),
    ("clock", "bridges"): ("clock", "HostTimes' own methods"),
}
#: Attributes only their own module may touch.
PRIVATE_TO = {"_samples_at_tick": "health"}


def reach_ins(root: Path) -> list[str]:
    """Every ``x.owner.attribute`` of :data:`REACH_INS` outside its owner's module, and every
    attribute of :data:`PRIVATE_TO` touched outside its module, in the daemon's modules."""
    found = []
    for path in sorted((root / "daemon").glob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
        for node in sorted((n for n in ast.walk(tree) if isinstance(n, ast.Attribute)),
                           key=lambda n: (n.lineno, n.col_offset)):
            pair = (node.value.attr, node.attr) if isinstance(node.value, ast.Attribute) else None
            if pair in REACH_INS and REACH_INS[pair][0] != path.stem:
                found.append(f"daemon/{path.name}:{node.lineno}: reaches into {'.'.join(pair)} "
                             f"(use {REACH_INS[pair][1]})")
            owner = PRIVATE_TO.get(node.attr)
            if owner is not None and path.stem != owner:
                found.append(f"daemon/{path.name}:{node.lineno}: touches {node.attr}, private to daemon/{owner}.py")
    return found


def test_no_daemon_module_reaches_into_another_owners_attributes() -> None:
    found = reach_ins(ROOT)
    assert not found, "\n".join(found)


def test_the_reach_in_check_catches_each_kind(tmp_path: Path) -> None:
    (tmp_path / "daemon").mkdir()
    (tmp_path / "daemon" / "pipeline.py").write_text(
        "def f(self, b):\n    w = self.ingress.dedupe.window\n    self.topology.nodes.pop(1, None)\n"
        "    b._samples_at_tick = 0\n    self.host.links['a'].write(b'')\n")
    (tmp_path / "daemon" / "health.py").write_text("def g(b):\n    b._samples_at_tick = 0\n")  # its own
    (tmp_path / "daemon" / "topology.py").write_text("def h(self):\n    self.nodes.pop(1, None)\n")  # its own
    got = reach_ins(tmp_path)
    assert got == ["daemon/pipeline.py:2: reaches into dedupe.window (use Ingress.dedupe_window())",
                   "daemon/pipeline.py:3: reaches into nodes.pop (use Topology.forget())",
                   "daemon/pipeline.py:4: touches _samples_at_tick, private to daemon/health.py",
                   "daemon/pipeline.py:5: reaches into host.links (use Host.send_command(): the service "
                   "writes on its links)"], got
