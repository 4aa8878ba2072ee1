"""One root error: every error a layer raises on purpose is a CellbridgeError (and a ValueError)."""

from __future__ import annotations

import pytest
from cellbridge.daemon.core.config import ConfigError, parse_config
from cellbridge.daemon.core.control import RequestError
from cellbridge.daemon.ops.security import SecurityError
from cellbridge.emulator.mesh.mesh import MeshError, parse_mesh
from cellbridge.emulator.world.world import ScenarioError
from cellbridge.protocol import ProtocolError, decode

from cellbridge.errors import CellbridgeError


@pytest.mark.parametrize("kind", [ProtocolError, ConfigError, MeshError, ScenarioError, SecurityError, RequestError])
def test_each_layers_error_is_a_cellbridge_error_and_a_value_error(kind: type) -> None:
    assert issubclass(kind, CellbridgeError) and issubclass(kind, ValueError)


def test_one_except_catches_what_different_layers_raise() -> None:
    caught = []
    for bad in (lambda: decode(b"\x01\x02"), lambda: parse_config({"pub": {"hwm": -1}}),
                lambda: parse_mesh("[[bridge]]\nid = 'x'\n")):
        try:
            bad()
        except CellbridgeError as exc:
            caught.append(type(exc))
    assert caught == [ProtocolError, ConfigError, MeshError]
