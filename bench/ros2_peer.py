"""A second DDS participant for the ROS 2 tests, with its own types, and the bags' type store.

Its types are not cellbridge's (``cellbridge.ros2.types``): they are generated here from
the ``.msg`` text by another parser (rosbags'), the shipped ``tactile_msgs`` text for
tactile_msgs and ROS 2 Humble's own definitions (as rosbags carries them) for the
standard messages; a class per message with the ROS 2 DDS type name. So a field that
cellbridge put in the wrong order, or gave the wrong type, does not decode here.

The peer talks DDS on loopback only (unicast discovery to 127.0.0.1, no multicast), as
the tests' every socket.
"""

from __future__ import annotations

import time
from dataclasses import field, make_dataclass
from typing import Any

from cyclonedds.core import Policy
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as idl
from cyclonedds.qos import Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype

from cellbridge.ros2 import msgdefs

TACTILE = ("tactile_msgs/msg/TactileState", "tactile_msgs/msg/TactileContact", "tactile_msgs/msg/TactileContacts")
LOOPBACK_ONLY = ("<CycloneDDS><Domain Id=\"any\"><General><Interfaces><NetworkInterface name=\"lo\"/></Interfaces>"
                 "<AllowMulticast>false</AllowMulticast></General><Discovery><ParticipantIndex>auto</ParticipantIndex>"
                 "<MaxAutoParticipantIndex>32</MaxAutoParticipantIndex><Peers><Peer Address=\"127.0.0.1\"/></Peers>"
                 "</Discovery></Domain></CycloneDDS>")
_PRIMITIVE = {"bool": bool, "byte": idl.byte, "char": idl.uint8, "int8": idl.int8, "uint8": idl.uint8,
              "int16": idl.int16, "uint16": idl.uint16, "int32": idl.int32, "uint32": idl.uint32,
              "int64": idl.int64, "uint64": idl.uint64, "float32": idl.float32, "float64": idl.float64,
              "string": str}


def typestore() -> Any:
    """ROS 2 Humble's types, and tactile_msgs from the shipped .msg text (rosbags' parser)."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    defs: dict[str, Any] = {}
    for name in TACTILE:
        defs.update(get_types_from_msg(msgdefs.text(name), name))
    store.register(defs)
    return store


class PeerTypes:
    """DDS classes generated from a rosbags type store's field definitions."""

    def __init__(self, store: Any) -> None:
        self.store = store
        self.classes: dict[str, type] = {}

    def __getitem__(self, name: str) -> type:
        if name not in self.classes:
            self.classes[name] = self._make(name)
        return self.classes[name]

    def _field_type(self, node: tuple[Any, Any]) -> Any:
        kind, detail = node
        if kind == Nodetype.BASE:
            return _PRIMITIVE[detail[0]]
        if kind == Nodetype.NAME:
            return self[detail]
        if kind == Nodetype.SEQUENCE:
            return idl.sequence[self._field_type(detail[0])]  # type: ignore[misc]  # generic at run time, not in its types
        if kind == Nodetype.ARRAY:
            return idl.array[self._field_type(detail[0]), detail[1]]  # type: ignore[misc]  # as above
        raise TypeError(f"no DDS type for {node}")

    def _make(self, name: str) -> type:
        _, fields = self.store.fielddefs[name]
        pkg, _, msg = name.split("/")
        spec = [(fname, self._field_type(node), field(default=None)) for fname, node in fields]
        # the type name ROS 2 gives it on DDS (Cyclone DDS reads it from the namespace)
        return make_dataclass(f"Peer_{pkg}_{msg}", spec, bases=(IdlStruct,),
                              namespace={"__module__": __name__, "__idl_typename__": f"{pkg}::msg::dds_::{msg}_"})


class Peer:
    """A DDS participant on ``domain`` reading ROS 2 topics into lists."""

    def __init__(self, domain: int, store: Any | None = None) -> None:
        self.types = PeerTypes(store or typestore())
        self._domain = Domain(domain, LOOPBACK_ONLY)
        self.participant = DomainParticipant(domain)
        self.readers: dict[str, DataReader] = {}
        self.got: dict[str, list[tuple[float, Any]]] = {}

    def subscribe(self, topic: str, ros_type: str, reliable: bool) -> None:
        """Read ``topic`` (a ROS 2 name) of ``ros_type``; best effort or reliable as ROS 2 readers ask."""
        qos = Qos(Policy.Reliability.Reliable(duration(seconds=1)) if reliable else Policy.Reliability.BestEffort,
                  Policy.History.KeepLast(1000), Policy.Durability.Volatile)
        t: Topic[Any] = Topic(self.participant, "rt" + topic, self.types[ros_type])
        self.readers[topic] = DataReader(self.participant, t, qos=qos)
        self.got[topic] = []

    def pump(self, seconds: float, until: Any = None) -> bool:
        """Take samples for ``seconds``, or until ``until(topic, sample)`` is true (then True)."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            for topic, reader in self.readers.items():
                for sample in reader.take(N=1000):
                    self.got[topic].append((time.time(), sample))
                    if until is not None and until(topic, sample):
                        return True
            time.sleep(0.005)
        return False

    def writers(self, topic: str) -> int:
        """How many writers the reader of ``topic`` is matched with now."""
        return len(self.readers[topic].get_matched_publications())

    def close(self) -> None:
        for entity in (self.participant, self._domain):
            entity.__del__()
