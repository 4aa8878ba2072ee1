"""What the daemon's core hands its shell: frozen messages, one class per kind.

:class:`~cellbridge.daemon.core.pipeline.Pipeline` never publishes, logs or writes: it
returns these, in order, and the shell does what each says (h11's events play the same
part for HTTP). A message is frozen; its ``payload`` is a fresh dict the shell may hand
to msgpack as it is, and a shell that adds fields (health's shell counters) builds a new
message with :meth:`Publish.with_fields`, never edits one in place.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

SCHEMA_VERSION = 2  # 2: contacts in link frames (link, position, normal, force_vector), topology.skin


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
    """``contact``: the contacts of one skin frame (see :mod:`cellbridge.daemon.core.readings`)."""

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

_P = TypeVar("_P", bound=Publish)


class Stamps:
    """Each topic's sequence numbers and the wall-clock stamps of what is published.

    The core runs on one time base, the host's monotonic clock as the shell passes it:
    silence, frames and deadlines never see the wall clock step. Wall-clock time is only
    stamped on what is published: that time + :attr:`wall_offset` (wall-clock minus the
    time base; 0 when fed wall-clock or recorded times)."""

    def __init__(self) -> None:
        self.wall_offset = 0.0
        self.seq: dict[str, int] = {}

    def message(self, kind: type[_P], now: float, body: dict[str, Any]) -> _P:
        """A ``kind`` message at ``now`` (time base) with ``body``'s fields: ``v``, ``seq`` (per
        topic, from 0), ``t_host`` (wall clock) first."""
        n = self.seq.get(kind.topic, 0)
        self.seq[kind.topic] = n + 1
        return kind({"v": SCHEMA_VERSION, "seq": n, "t_host": now + self.wall_offset, **body})

    def wall(self, t: float | None) -> float | None:
        """Time-base ``t`` on the wall clock (None stays None)."""
        return None if t is None else t + self.wall_offset
