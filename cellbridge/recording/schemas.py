"""JSON Schemas of the daemon's topics (docs/zmq-api.md), as written into MCAP files.

One schema per topic, named ``cellbridge.<topic>`` and stored with encoding
``jsonschema`` next to ``json`` channels: what Foxglove reads. The schemas describe the
fields the API documents and admit the rest (``additionalProperties``): within a schema
version fields are only added, and a recording of a newer daemon must still be valid.
A non-finite float is the string ``"NaN"``, ``"Infinity"`` or ``"-Infinity"``
(:mod:`cellbridge.recording.codec`), so every float field is a number or one of those.
"""

from __future__ import annotations

import json
from typing import Any

SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"

FLOAT: dict[str, Any] = {"anyOf": [{"type": "number"}, {"enum": ["NaN", "Infinity", "-Infinity"]}]}
INT: dict[str, Any] = {"type": "integer"}
BOOL: dict[str, Any] = {"type": "boolean"}


def _array(items: dict[str, Any], doc: str) -> dict[str, Any]:
    return {"type": "array", "items": items, "description": doc}


def _payload(topic: str, doc: str, properties: dict[str, Any], required: list[str],
             t_bridge: dict[str, Any] | None = None) -> dict[str, Any]:
    common = {
        "v": {**INT, "description": "schema version of the payload"},
        "seq": {**INT, "description": "per-topic message counter from 0 at daemon start"},
        "t_host": {**FLOAT, "description": "s since the Unix epoch (host time)"},
        "t_bridge": t_bridge if t_bridge is not None else {"type": "null"},
        "source": {"type": "string", "description": "the daemon that published it (pub.source, default its host name)"},
    }
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": f"cellbridge.{topic}",
        "description": doc,
        "type": "object",
        "properties": {**common, **properties},
        "required": ["v", "seq", "t_host", *required],
        "additionalProperties": True,
    }


_COLUMN_INTS = ("bridge", "element", "cycle")
_ELEMENT_FLOATS = ("t_sample", "c1", "c2", "dc1", "dc2", "force", "area")

CONTACT_ITEM: dict[str, Any] = {
    "type": "object",
    "properties": {
        "id": INT, "age": INT, "missed": INT, "t": FLOAT,
        **{k: FLOAT for k in ("x", "y", "force", "area", "diameter", "centroid_x", "centroid_y", "model_x",
                              "model_y", "sigma_x", "sigma_y", "sigma_xy", "sigma_force", "sigma_diameter",
                              "pressure", "force_sum", "chi2", "t_sample")},
        "elements": _array(INT, "ids of the touched elements (bridge ids)"),
        "unknown_near": _array(INT, "ids of the unknown elements among its elements and their neighbours"),
        "valid": BOOL, "fit_ok": BOOL,
    },
    "required": ["id", "x", "y", "force", "elements", "valid"],
    "additionalProperties": True,
}

SCHEMAS: dict[str, dict[str, Any]] = {
    "element": _payload(
        "element", "per-element capacitance, force and area; columnar, one entry per sample",
        {**{k: _array(INT, k) for k in _COLUMN_INTS},
         **{k: _array(FLOAT, k) for k in _ELEMENT_FLOATS},
         "valid": _array(BOOL, "the inverse found a unique (force, area)"),
         "status": _array(INT, "why not valid (bits)"),
         "touched": _array(BOOL, "the element is in contact")},
        ["bridge", "c1", "c2", "force", "area", "valid"],
        t_bridge=_array(FLOAT, "s, bridge time of each sample")),
    "raw": _payload(
        "raw", "readings as the bridges sent them; columnar",
        {"link": {"type": "string"}, **{k: _array(INT, k) for k in _COLUMN_INTS},
         **{k: _array(FLOAT, k) for k in ("c1", "c2")},
         **{k: _array(INT, k) for k in ("flags", "mode", "oversampling")}},
        ["link", "bridge", "c1", "c2"],
        t_bridge=_array(FLOAT, "s, bridge time of each sample")),
    "contact": _payload(
        "contact", "contacts of one skin frame",
        {"t_sample": FLOAT, "contacts": _array(CONTACT_ITEM, "one map per contact")},
        ["t_sample", "contacts"]),
    "health": _payload("health", "the daemon's health (every [health] interval)",
                       {"links": {"type": "object"}, "bridges": {"type": "object"}}, []),
    "topology": _payload("topology", "the mesh and the layout, when they change",
                         {"bridges": {"type": "object"}, "gateways": {"type": "object"}}, []),
    "serial": _payload(
        "serial", "one read of a gateway line, the bytes exactly as read (re-run the daemon on them)",
        {"link": {"type": "string", "description": "the link's name in the daemon config"},
         "t_read": {"type": "number", "description": "the read's arrival on the clock a replay runs on: the "
                                                     "wall clock's at the daemon's start, then the monotonic clock's"},
         "data": {"type": "string", "contentEncoding": "base64", "description": "the bytes read"}},
        ["link", "data"]),
}

#: For a topic the schemas do not know (a newer daemon): any JSON object.
GENERIC: dict[str, Any] = {"$schema": "https://json-schema.org/draft/2020-12/schema", "type": "object"}


def schema_for(topic: str) -> dict[str, Any]:
    return SCHEMAS.get(topic, {**GENERIC, "title": f"cellbridge.{topic}"})


def schema_bytes(topic: str) -> bytes:
    return json.dumps(schema_for(topic), separators=(",", ":")).encode()
