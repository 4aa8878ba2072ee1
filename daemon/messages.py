"""What the daemon's core hands its shell: frozen messages, one class per kind.

:class:`~cellbridge.daemon.pipeline.Pipeline` never publishes, logs or writes: it
returns these, in order, and the shell does what each says (h11's events play the same
part for HTTP). A message is frozen; its ``payload`` is a fresh dict the shell may hand
to msgpack as it is, and a shell that adds fields (health's shell counters) builds a new
message with :meth:`Publish.with_fields`, never edits one in place.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar


@dataclass(frozen=True, slots=True)
class Publish:
    """A message for the PUB socket: ``topic`` (class-wide) and its msgpack-ready ``payload``
    (``v``, ``seq``, ``t_host`` and the topic's fields, as docs/zmq-api.md lists them)."""

    topic: ClassVar[str] = ""
    payload: dict[str, Any]

    def with_fields(self, fields: dict[str, Any]) -> Publish:
        """The same message with ``fields`` added (after the core's own)."""
        return type(self)({**self.payload, **fields})


class ElementBatch(Publish):
    """``element``: calibrated ΔC, force, area and touch of every placed sample of one read."""

    __slots__ = ()
    topic = "element"


class RawBatch(Publish):
    """``raw``: every sample of one read as it came off the line (counts or ADC sums)."""

    __slots__ = ()
    topic = "raw"


class Health(Publish):
    """``health``: links, bridges, layout, reassembly and command counters."""

    __slots__ = ()
    topic = "health"


class Topology(Publish):
    """``topology``: the routing tree, each bridge's gateway and link, and the layout."""

    __slots__ = ()
    topic = "topology"


class ContactFrame(Publish):
    """``contact``: the contacts of one skin frame (see :mod:`cellbridge.daemon.readings`)."""

    __slots__ = ()
    topic = "contact"


@dataclass(frozen=True, slots=True)
class LogEvent:
    """Something an operator should read in the log: ``level`` is a :mod:`logging` level name."""

    level: str
    text: str
    fields: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class LinkWrite:
    """Bytes (a COBS-framed command) to write on the link named ``link``."""

    link: str
    data: bytes


#: Everything :meth:`Pipeline.feed` and its siblings return.
Message = Publish | LogEvent | LinkWrite
