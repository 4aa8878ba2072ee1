"""The thin DDS shell: our topics on the ROS 2 graph, through Cyclone DDS, no ROS install.

ROS 2 maps a topic ``/cellbridge/contacts`` of type ``tactile_msgs/msg/TactileContacts`` to
the DDS topic ``rt/cellbridge/contacts`` of type ``tactile_msgs::msg::dds_::TactileContacts_``
(:mod:`cellbridge.ros2.types`), plain CDR; a DDS writer that does the same is a ROS 2
publisher to every ROS 2 node on the domain (``ros2 topic list`` shows it, with no node name).

Where DDS talks (:func:`dds_config`): on loopback by default, as every cellbridge socket
is: discovery by unicast to 127.0.0.1 (participant indices found automatically), no
multicast, so nothing leaves the machine and ROS 2 nodes on this machine find it. On a
named interface (``--interface eth0``): Cyclone DDS's defaults there (multicast discovery),
to reach ROS 2 nodes on other machines. Or a whole Cyclone DDS configuration of the user's
(``--dds-config``).
"""

from __future__ import annotations

import re
import socket
from typing import Any

from cyclonedds.core import DDSException, Policy
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Qos
from cyclonedds.topic import Topic
from cyclonedds.util import duration

from cellbridge.ros2.qos import RELIABLE, TopicSpec

LOOPBACK = "lo"
#: How long a reliable write may wait for a slow subscriber before it is counted as dropped.
MAX_BLOCKING = duration(milliseconds=20)
DOMAIN_MAX = 232  # ROS 2's domain ids: 0..232 (DDS ports 7400 + 250 * domain stay below 65536)


class BadInterface(ValueError):
    """An interface name DDS cannot be configured with."""


def dds_config(interface: str = LOOPBACK, max_participants: int = 32) -> str:
    """The Cyclone DDS configuration (XML) for ``interface``: see the module's docstring."""
    if not re.fullmatch(r"[A-Za-z0-9_.:-]{1,32}", interface):
        raise BadInterface(f"{interface!r} is not a network interface name")
    if interface == LOOPBACK:
        return ("<CycloneDDS><Domain Id=\"any\"><General><Interfaces><NetworkInterface name=\"lo\"/></Interfaces>"
                "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
                f"<MaxAutoParticipantIndex>{max_participants}</MaxAutoParticipantIndex>"
                "<Peers><Peer Address=\"127.0.0.1\"/></Peers></Discovery></Domain></CycloneDDS>")
    names = [name for _, name in socket.if_nameindex()]
    if interface not in names and ":" not in interface:  # (an alias label, eth0:1, is not listed)
        raise BadInterface(f"{interface!r}: no such network interface here (interfaces: {', '.join(names)})")
    return (f"<CycloneDDS><Domain Id=\"any\"><General><Interfaces><NetworkInterface name=\"{interface}\"/>"
            "</Interfaces></General></Domain></CycloneDDS>")


def writer_qos(spec: TopicSpec) -> Qos:
    """The topic's QoS (:mod:`cellbridge.ros2.qos`) as DDS policies, plain CDR as ROS 2 writes it."""
    reliability = (Policy.Reliability.Reliable(max_blocking_time=MAX_BLOCKING) if spec.reliability == RELIABLE
                   else Policy.Reliability.BestEffort)
    return Qos(reliability, Policy.Durability.Volatile, Policy.History.KeepLast(spec.depth),
               Policy.DataRepresentation(use_cdrv0_representation=True))


class Graph:
    """A DDS participant on ``domain`` with one writer per topic.

    :meth:`publish` never raises for a write DDS refuses (a reliable subscriber that keeps
    the writer's history full for longer than ``MAX_BLOCKING``): the message is counted in
    :attr:`dropped` instead."""

    def __init__(self, domain: int, specs: dict[str, TopicSpec], config: str) -> None:
        if not 0 <= domain <= DOMAIN_MAX:
            raise ValueError(f"--domain must be within 0..{DOMAIN_MAX} (ROS_DOMAIN_ID), got {domain}")
        self.specs = specs
        self._domain = Domain(domain, config)
        self.participant = DomainParticipant(domain)
        self.writers: dict[str, DataWriter] = {}
        for key, spec in specs.items():
            topic: Topic[Any] = Topic(self.participant, spec.dds_name, spec.message_class)
            self.writers[key] = DataWriter(self.participant, topic, qos=writer_qos(spec))
        self.published: dict[str, int] = {k: 0 for k in specs}
        self.dropped: dict[str, int] = {k: 0 for k in specs}

    def publish(self, key: str, message: Any) -> None:
        try:
            self.writers[key].write(message)
            self.published[key] += 1
        except DDSException:
            self.dropped[key] += 1

    def matched(self, key: str) -> int:
        """How many readers (subscribers) the topic's writer has now."""
        return len(self.writers[key].get_matched_subscriptions())

    def close(self) -> None:
        """Delete the participant (and with it every writer: subscribers see them go) and the domain."""
        for entity in (self.participant, self._domain):
            entity.__del__()
        self.writers.clear()
