"""Reading a skin description (the file I/O :mod:`cellbridge.tactile.skin_geometry` leaves
out), with the link frames of the robot's URDF when it names one.

A URDF is read with yourdfpy (a maintained URDF parser: joints' origins in the URDF's
roll-pitch-yaw convention, mimic and fixed joints, the validation of the robot's tree), in
the optional ``robot`` extra: only a description naming a URDF needs it, and then a
missing yourdfpy is an error saying how to install it.
"""

from __future__ import annotations

import io
import logging
import tomllib
from os import PathLike
from pathlib import Path
from typing import Any
from xml.etree import ElementTree

import numpy as np
from cellbridge.tactile.skin_geometry import LinkFrame, SkinError, SkinGeometry, skin_from_mapping

__all__ = ["MAX_FILE_BYTES", "is_skin_file", "load_skin", "read_bounded", "urdf_links"]


#: Bytes a skin description or layout file may have: a layout of every bridge id (65 534)
#: is about 5 MB, a skin description of 4096 patches about 1. A file past it (a gigabyte,
#: /dev/zero) is refused after this much is read, not read whole into memory and parsed.
MAX_FILE_BYTES = 16 * 2**20


def read_bounded(path: str | PathLike[str], what: str) -> str:
    """The text of a user's file (at most :data:`MAX_FILE_BYTES`); a missing, unreadable or
    larger file, or one not UTF-8, is a :class:`SkinError` (a ``ValueError``) naming it."""
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise SkinError(f"{path}: cannot read {what}: {exc.strerror}") from None
    if len(data) > MAX_FILE_BYTES:
        raise SkinError(f"{path}: {what} too large (more than {MAX_FILE_BYTES} bytes)")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise SkinError(f"{path}: {what} is not UTF-8 text") from None


def urdf_links(path: str | PathLike[str]) -> list[LinkFrame]:
    """The links of a URDF file: name, parent link and the joint's origin (4×4) between them."""
    try:
        import yourdfpy  # type: ignore[import-untyped]  # no type information published
    except ImportError:
        raise SkinError(f"{path}: reading a URDF needs yourdfpy: pip install 'cellbridge[robot]'") from None
    if not Path(path).is_file():
        raise SkinError(f"{path}: cannot read URDF: no such file")
    text = read_bounded(path, "URDF")
    # Strict XML first: yourdfpy, on a parse error, logs it and parses again recovering what
    # it can, so a file cut short gave its last joint no origin (the link at its parent's)
    # and only a log line said so. A URDF declares no DTD: one (entities to expand, files
    # or addresses to fetch) is refused before any parser sees it.
    if "<!DOCTYPE" in text or "<!ENTITY" in text:
        raise SkinError(f"{path}: not a URDF it can read: it declares a DTD (<!DOCTYPE or <!ENTITY)")
    try:
        ElementTree.fromstring(text)
    except ElementTree.ParseError as exc:
        raise SkinError(f"{path}: not a URDF it can read: not well-formed XML: {exc}") from None
    data = text.encode("utf-8")
    quiet = logging.getLogger("yourdfpy")
    level = quiet.level
    quiet.setLevel(logging.CRITICAL)  # what it would log is in the error raised here
    try:
        robot = yourdfpy.URDF.load(io.BytesIO(data), mesh_dir=str(Path(path).parent), load_meshes=False,
                                   build_scene_graph=False, build_collision_scene_graph=False,
                                   load_collision_meshes=False)
    except Exception as exc:  # yourdfpy raises many kinds for a bad file; each is a bad URDF here
        raise SkinError(f"{path}: not a URDF it can read: {exc}") from None
    finally:
        quiet.setLevel(level)
    # One pose per link: a link described twice, or the child of two joints, has two (the
    # last read was taken, silently).
    parent_of: dict[str, Any] = {}
    for j in robot.robot.joints:
        if j.child in parent_of:
            raise SkinError(f"{path}: link {j.child!r} is the child of two joints ({parent_of[j.child].name!r}, "
                            f"{j.name!r})")
        parent_of[j.child] = j
    seen: set[str] = set()
    for link in robot.robot.links:
        if link.name in seen:
            raise SkinError(f"{path}: link {link.name!r} is described twice")
        seen.add(link.name)
    out = []
    for link in robot.robot.links:
        j = parent_of.get(link.name)
        origin = np.eye(4) if j is None or j.origin is None else np.asarray(j.origin, dtype=np.float64)
        out.append(LinkFrame(link.name, None if j is None else j.parent,
                             tuple(tuple(float(v) for v in row) for row in origin)))
    return out


def is_skin_file(text: str) -> bool:
    """Whether a TOML text is a skin description (it has ``[[patch]]`` tables); a text that
    is no TOML is not (its reader says why)."""
    try:
        return "patch" in tomllib.loads(text)
    except (tomllib.TOMLDecodeError, RecursionError):  # (nested arrays are parsed recursively)
        return False


def load_skin(path: str | PathLike[str]) -> SkinGeometry:
    """Read and validate a skin description, and the URDF it names (relative to the file).

    Every problem, a missing file included, is a :class:`SkinError` naming the file."""
    text = read_bounded(path, "skin description")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SkinError(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:  # tomllib parses nested arrays and tables recursively
        raise SkinError(f"{path}: not valid TOML: nested too deeply") from None
    links = None
    urdf = data.get("urdf")
    if isinstance(urdf, str) and urdf:
        links = urdf_links(Path(path).parent / urdf)
    return skin_from_mapping(data, str(path), links)
