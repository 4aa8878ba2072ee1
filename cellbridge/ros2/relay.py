"""What ``cellbridge ros2`` does with the daemon's messages, in which order: contacts first.

The bridge to ROS 2 is one Python thread. Most of its work is large and slow next to a
contact: on a 16x16 skin a ``health`` message (256 bridges) costs tens of milliseconds
to convert and serialise, a skin picture (markers) about ten, and a busy machine
stretches that several times. A contact that arrives while such a message is being
worked on must not wait for the whole batch that was drained with it.

:class:`Relay` therefore takes one message of other work at a time and, after each, looks
at the subscriber socket again: every contact waiting there (or already drained) is
published before the next piece of other work. A contact waits at most for the one
message in progress when it arrived, whatever the backlog behind it. The other
messages keep their order among themselves; nothing is skipped or dropped here (the
socket's own bounded queue counts what a subscriber that falls behind loses).

The relay holds no socket of its own: it is fed by a :class:`cellbridge.views.source.Source`
(anything with ``poll`` and ``drain``) and hands each ROS 2 message to ``publish``
(:meth:`cellbridge.ros2.graph.Graph.publish`), so it runs in-process in the tests.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

from cellbridge.ros2.convert import Converter
from cellbridge.ros2.daemon_feed import PayloadModel

CONTACT = "contact"


class Feed(Protocol):
    """The daemon's stream as the relay reads it (:class:`cellbridge.views.source.Source`)."""

    def poll(self, timeout_ms: int) -> bool: ...

    def drain(self, model: Any, max_messages: int = ...) -> int: ...


class Relay:
    """Daemon messages from ``source`` through ``converter`` to ``publish(key, message)``.

    :meth:`step` is one turn of the loop; :attr:`stop` (a callable) ends a turn early, between
    two messages (a signal asked the process to stop)."""

    def __init__(self, source: Feed, model: PayloadModel, converter: Converter,
                 publish: Callable[[str, Any], None], stop: Callable[[], bool] = lambda: False) -> None:
        self.source = source
        self.model = model
        self.converter = converter
        self.publish = publish
        self.stop = stop
        self.contacts: deque[tuple[str, Any, float]] = deque()
        self.others: deque[tuple[str, Any, float]] = deque()

    def _take(self) -> None:
        """Whatever waits on the socket, sorted into the two queues (each in arrival order)."""
        self.source.drain(self.model)
        for m in self.model.take():
            (self.contacts if m[0] == CONTACT else self.others).append(m)

    def _emit(self, topic: str, payload: Any, now: float) -> None:
        for key, message in self.converter.feed(topic, payload, now):
            self.publish(key, message)

    def step(self, timeout_ms: int = 100) -> int:
        """Wait up to ``timeout_ms`` for messages, then work until none waits (or :attr:`stop`):
        every waiting contact before each next other message. Returns how many messages it handled."""
        self.source.poll(timeout_ms)
        self._take()
        done = 0
        while (self.contacts or self.others) and not self.stop():
            while self.contacts:
                self._emit(*self.contacts.popleft())
                done += 1
            if self.others:
                self._emit(*self.others.popleft())
                done += 1
                self._take()  # contacts that came meanwhile go before the next piece of work
        return done
