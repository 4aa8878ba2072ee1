"""The ROS 2 message definitions we publish, as ``.msg`` text, and what is built from it.

The ``.msg`` files live in ``cellbridge/ros2/interfaces/<package>/msg/<Name>.msg``:
``tactile_msgs`` (a ROS 2 package as it stands: ``colcon build`` it in a workspace to
echo our topics typed) and the standard messages it and our other topics use, field for
field those of ROS 2 Humble and Jazzy (the two are the same on the wire for these).

An MCAP file of the ``ros2`` profile stores, per type, the ``ros2msg`` schema: the type's
own text, then the text of every type it uses, each after a line of 80 ``=`` and a line
``MSG: package/Name`` (what rosbag2 writes, what rosbags and Foxglove read).
"""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path

INTERFACES = Path(__file__).resolve().parent / "interfaces"
SEPARATOR = "=" * 80
#: The primitive types of the .msg language: anything else is a message type.
PRIMITIVES = frozenset({"bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16",
                        "int32", "uint32", "int64", "uint64", "string", "wstring"})


class UnknownMessageType(LookupError):
    """A message type we ship no ``.msg`` for (``package/msg/Name`` or ``package/Name``)."""


def short(name: str) -> str:
    """``tactile_msgs/msg/TactileState`` -> ``tactile_msgs/TactileState`` (the form in .msg text)."""
    pkg, _, rest = name.partition("/")
    return f"{pkg}/{rest.rsplit('/', 1)[-1]}"


def full(name: str) -> str:
    """``tactile_msgs/TactileState`` -> ``tactile_msgs/msg/TactileState`` (the form of a ROS 2 type name)."""
    pkg, _, rest = name.partition("/")
    return f"{pkg}/msg/{rest.rsplit('/', 1)[-1]}"


@cache
def text(name: str) -> str:
    """The ``.msg`` text of a type, as shipped."""
    pkg, _, msg = short(name).partition("/")
    path = INTERFACES / pkg / "msg" / f"{msg}.msg"
    if not path.is_file():
        raise UnknownMessageType(f"no .msg for {name} (looked for {path})")
    return path.read_text()


def _base_type(field_type: str) -> str:
    """``geometry_msgs/Point[]`` -> ``geometry_msgs/Point``; ``string<=5`` -> ``string``."""
    return re.split(r"[\[<]", field_type, maxsplit=1)[0]


def dependencies(name: str) -> list[str]:
    """The message types ``name``'s fields use (short names), each once, depth first in
    the order the fields name them (the order rosbag2 writes them)."""
    out: list[str] = []

    def visit(n: str) -> None:
        for line in text(n).splitlines():
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            base = _base_type(line.split()[0])
            if base in PRIMITIVES:  # constants among them: only primitive types have constants
                continue
            if "/" not in base:  # a type of the same package
                base = f"{short(n).split('/')[0]}/{base}"
            if base not in out:
                out.append(base)
                visit(base)

    visit(short(name))
    return out


@cache
def schema(name: str) -> str:
    """The ``ros2msg`` schema text of ``name``: its .msg and those of all it uses."""
    parts = [text(name).rstrip("\n")]
    for dep in dependencies(name):
        parts.append(f"{SEPARATOR}\nMSG: {dep}\n{text(dep).rstrip(chr(10))}")
    return "\n".join(parts) + "\n"


def shipped() -> list[str]:
    """Every type we ship a .msg for (full names, sorted)."""
    return sorted(f"{p.parent.parent.name}/msg/{p.stem}" for p in INTERFACES.glob("*/msg/*.msg"))
