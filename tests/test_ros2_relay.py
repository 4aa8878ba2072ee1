"""The order ``cellbridge ros2`` publishes in: a contact never waits for a backlog of large messages.

In-process, with the views' real ZeroMQ shell (:class:`cellbridge.views.source.Source`) on a
real PUB socket on loopback; the relay hands its ROS 2 messages to a list instead of DDS
(the order of the calls is the question here, not DDS). Bounds are counted in messages of
work, not in wall time.
"""

from __future__ import annotations

import math
import time
from typing import Any

import msgpack
import pytest
import zmq

pytest.importorskip("cyclonedds", reason="the ros2 extra is not installed (make install installs it)")

from cellbridge.ros2.convert import Converter
from cellbridge.ros2.daemon_feed import PayloadModel
from cellbridge.ros2.relay import Relay
from cellbridge.views.source import Source
from daemon_harness import free_port

N = 256  # a 16x16 skin


def health(seq: int, t: float) -> dict[str, Any]:
    bridges = {str(b): {"link": "gw", "silent": False, "frames": 400, "lost": 0, "loss": 0.0,
                        "sample_rate": 100.0, "age": 0.01} for b in range(1, N + 1)}
    return {"v": 1, "seq": seq, "t_host": t, "uptime": 10.0, "links": {"gw": {"connected": True}},
            "bridges": bridges, "source": "skin"}


def element(seq: int, t: float) -> dict[str, Any]:
    return {"v": 1, "seq": seq, "t_host": t, "bridge": list(range(1, N + 1)), "force": [0.0] * N,
            "area": [0.0] * N, "dc1": [1e-14] * N, "dc2": [1e-14] * N, "valid": [False] * N, "status": [8] * N,
            "touched": [False] * N, "t_sample": [t] * N, "source": "skin"}


def contact(seq: int, t: float) -> dict[str, Any]:
    return {"v": 1, "seq": seq, "t_host": t, "t_sample": t - 0.01, "source": "skin",
            "contacts": [{"id": 7, "x": 0.04, "y": 0.02, "force": 2.0, "valid": True, "diameter": 0.01}]}


class Daemon:
    """A PUB socket on loopback standing in for the daemon, and the relay's Source on it."""

    def __init__(self) -> None:
        self.ctx = zmq.Context()
        self.pub = self.ctx.socket(zmq.PUB)
        self.pub.linger = 0
        port = self.pub.bind_to_random_port("tcp://127.0.0.1")
        self.source = Source(f"tcp://127.0.0.1:{port}", f"tcp://127.0.0.1:{free_port()}")
        self.seq: dict[str, int] = {}
        self.sent = 0  # every message's time: 1.7e9 + how many went before it

    def send(self, topic: str) -> None:
        seq = self.seq[topic] = self.seq.get(topic, -1) + 1
        self.sent += 1
        body = {"health": health, "element": element, "contact": contact}[topic](seq, 1.7e9 + self.sent)
        self.pub.send_multipart([topic.encode(), msgpack.packb(body)])

    def joined(self, model: PayloadModel) -> None:
        """Until the subscriber gets what is sent (ZeroMQ's subscription takes a moment to reach the PUB)."""
        end = time.monotonic() + 30
        while time.monotonic() < end:
            self.send("health")
            if self.source.poll(50):
                self.source.drain(model)
                model.take()
                return
        raise AssertionError("the subscriber never joined")

    def drained(self, model: PayloadModel, n: int) -> None:
        """Until ``n`` messages wait in ``model`` (drained from the socket, not yet taken)."""
        end = time.monotonic() + 30
        while len(model.pending) < n and time.monotonic() < end:
            if self.source.poll(100):
                self.source.drain(model)
        assert len(model.pending) == n

    def close(self) -> None:
        self.source.close()
        self.ctx.destroy(linger=0)


@pytest.fixture
def daemon() -> Any:
    d = Daemon()
    try:
        yield d
    finally:
        d.close()


def test_a_contact_that_arrives_during_a_backlog_goes_out_after_at_most_the_message_in_progress(daemon: Daemon) -> None:
    converter = Converter(marker_period=math.inf)
    model = PayloadModel(converter)
    daemon.joined(model)
    backlog = 20
    for i in range(backlog):  # large messages, drained in one batch as a loaded bridge finds them
        daemon.send("health" if i % 2 else "element")
    daemon.drained(model, backlog)
    published: list[str] = []

    def publish(key: str, message: Any) -> None:
        published.append(key)
        if len(published) == 1:  # the contact arrives while the first large message goes out
            daemon.send("contact")
            end = time.monotonic() + 30
            while not daemon.source.poll(100) and time.monotonic() < end:
                pass  # (the socket held nothing else: the backlog is drained)

    relay = Relay(daemon.source, model, converter, publish)
    end = time.monotonic() + 30
    while "contacts" not in published[1:] and time.monotonic() < end:
        relay.step(100)
    assert "contacts" in published, "the contact was never published"
    # before it: the message in progress when it arrived (one state or one diagnostics), nothing of the backlog
    assert published.index("contacts") == 1, published
    assert len([k for k in published if k != "contacts"]) == backlog  # and the backlog still all goes out after


def test_contacts_of_a_drained_batch_go_first_and_the_rest_keeps_its_order(daemon: Daemon) -> None:
    converter = Converter(marker_period=math.inf)
    model = PayloadModel(converter)
    daemon.joined(model)
    order = ["element", "health", "contact", "element", "contact", "health"]
    for topic in order:
        daemon.send(topic)
    daemon.drained(model, len(order))
    stamps: list[tuple[str, float]] = []
    relay = Relay(daemon.source, model, converter,
                  lambda key, m: stamps.append((key, m.header.stamp.sec if key != "contacts" else -1)))
    assert relay.step(0) == len(order)
    assert [k for k, _ in stamps] == ["contacts", "contacts", "state", "diagnostics", "state", "diagnostics"]
    others = [s for k, s in stamps if k != "contacts"]
    assert others == sorted(others)  # the daemon's order (t_host grows with seq)
