"""The daemon's stream as the ROS 2 side takes it: the views' model, keeping every payload.

:class:`PayloadModel` is a :class:`cellbridge.views.model.SkinView`, so the views' ZeroMQ
shell (:class:`cellbridge.views.source.Source`) drains into it as into any view: it counts
this subscriber's losses (gaps in ``seq``), notices a restarted daemon (its numbering
starts again) and then asks for the layout anew, as every view does. Besides, it keeps
each payload for :class:`cellbridge.ros2.convert.Converter` (:meth:`take`), and hands
it every layout (a ``topology`` message or the control socket's reply).

Only payloads of the daemon the model shows are kept (``source``: ``--source``, else the
first heard, as every view): behind a ``cellbridge proxy`` another daemon's contacts would
otherwise go out on the same topic, in the same frame, as if they were this skin's. The
others are counted (:attr:`other_sources`). A payload the converter is given is counted
as malformed by the converter alone: the view's own reading of it (which fails on the
same payloads) is not counted a second time.
"""

from __future__ import annotations

from typing import Any

from cellbridge.ros2.convert import Converter, newer_schema
from cellbridge.views.model import TOPICS, SkinView


class PayloadModel(SkinView):
    def __init__(self, converter: Converter, force_scale: float = 5.0, source: str | None = None) -> None:
        super().__init__(force_scale=force_scale, source=source)
        self.converter = converter
        self.pending: list[tuple[str, Any, float]] = []
        self._kept = False

    def _shown(self, source: Any) -> bool:
        self._kept = super()._shown(source)
        return self._kept

    def feed(self, topic: str, payload: Any, now: float) -> None:
        if isinstance(payload, dict) and newer_schema(payload):  # not even its layout is taken
            if topic in TOPICS and self._shown(payload.get("source")):
                self.converter.newer_schema += 1
                self.received[topic] = self.received.get(topic, 0) + 1
                self._count_seq(topic, payload)  # received, so its seq is no gap (losses stay true)
            return
        self._kept = False  # set by _shown: a map of a known topic from the daemon shown
        malformed, restarts = self.malformed, self.daemon_restarts
        try:
            super().feed(topic, payload, now)
        except ArithmeticError:  # a health figure past float range: the view's summary gives up on it
            self.malformed += 1
        if self._kept:
            self.malformed = malformed  # the converter counts what it cannot read
            if self.daemon_restarts != restarts and self.converter.contacts:
                self.pending.append(("contact", _ended(payload), now))
            self.pending.append((topic, payload, now))

    def _feed_element(self, p: dict[str, Any]) -> None:
        """Only whether an element the layout does not place is reporting (then the layout is
        asked for again): the readings themselves are the converter's (a view's per-element
        history would cost a third of the time a 16x16 skin's message takes here)."""
        bridges = p.get("bridge")
        if not isinstance(bridges, list):
            raise ValueError("element without bridge column")
        if self.layout and not self.needs_topology and any(b not in self.layout for b in bridges):
            self.needs_topology = True

    def _feed_health(self, p: dict[str, Any]) -> None:
        """Only the count: the converter makes the diagnostics of the payload itself (a view's
        bounded copy and summary of a 16x16 skin's health cost ~9 ms a message here, for nothing)."""
        self.health_count += 1

    def feed_topology(self, payload: dict[str, Any]) -> None:
        super().feed_topology(payload)
        self.converter.set_layout(payload)

    def take(self) -> list[tuple[str, Any, float]]:
        """The payloads fed since the last call, in order, as ``(topic, payload, time)``."""
        out, self.pending = self.pending, []
        self.converter.lost = self.lost
        return out


def _ended(health: dict[str, Any]) -> dict[str, Any]:
    """The ``contact`` message a daemon restarted under a press never sends: its contacts
    ended (``contacts: []``), at the new process's first health message. The old process
    published contacts while it had any and would have sent ``[]`` when they ended; it died
    first, and the new one has none to end: without this, the last TactileContacts (and the
    picture) said the skin was pressed until the next touch."""
    t = health.get("t_host")
    return {"v": health.get("v"), "source": health.get("source"), "t_host": t, "t_sample": t, "contacts": []}
