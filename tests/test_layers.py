"""The layers' import rules (the table of DESIGN.md, "Layout and names"), checked on the source.

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
    "emulator": ({"emulator", "protocol", "tactile"}, {"numpy", "msgpack", "zmq", "setproctitle"}),
    # mcap: the daemon takes a recording's serial channel as a link (``replay:FILE.mcap``)
    "daemon": ({"daemon", "protocol", "tactile"}, {"numpy", "msgpack", "zmq", "serial", "mcap"}),
}
#: The modules of the top package any layer may read: leaves without imports (version, root error).
SHARED = {"_version", "errors"}
#: Standard-library modules that would put I/O, event loops or clocks into the pure protocol layer.
IMPURE = {"asyncio", "socket", "selectors", "select", "serial", "threading", "time", "os", "subprocess", "io"}


def imports(path: Path, root: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in ``path`` (a module of the layer
    folders under ``root``); relative ones resolved, ``from cellbridge import x`` as
    ``cellbridge.x``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    package = ".".join(("cellbridge", *path.relative_to(root).parts[:-1]))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
            name = (f"{base}.{node.module}" if node.module else base) if node.level else node.module or ""
            if name == "cellbridge":
                out += [(node.lineno, f"cellbridge.{a.name}") for a in node.names]
            else:
                out.append((node.lineno, name))
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
    assert any("emulator/ imports cellbridge.daemon " in v for v in got)
    assert any("tactile/ imports zmq" in v for v in got)
