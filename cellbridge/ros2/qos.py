"""The ROS 2 topics we publish, their types and their QoS.

| key | ROS 2 topic (default namespace) | type | QoS |
|---|---|---|---|
| ``state`` | ``/cellbridge/tactile_state`` | ``tactile_msgs/msg/TactileState`` | sensor data: best effort, keep last 5 |
| ``contacts`` | ``/cellbridge/contacts`` | ``tactile_msgs/msg/TactileContacts`` | reliable, keep last 10 |
| ``markers`` | ``/cellbridge/markers`` | ``visualization_msgs/msg/MarkerArray`` | reliable, keep last 10 (rviz subscribes reliable) |
| ``diagnostics`` | ``/diagnostics`` | ``diagnostic_msgs/msg/DiagnosticArray`` | reliable, keep last 10 (where ROS 2's diagnostic tools look) |

All volatile. Readings are best effort as ROS 2's sensor-data profile: a late reading is
worth less than the next one. Contacts are reliable: a subscriber must not miss the
message that says a contact ended. A best-effort subscriber takes a reliable publisher's
messages; a reliable subscriber (``ros2 topic echo`` before Humble, rviz by default)
does not match a best-effort publisher: ask for best effort to read the readings.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

RELIABLE, BEST_EFFORT = "reliable", "best_effort"
#: rmw's enum values, as rosbag2 stores them in ``offered_qos_profiles``.
_RMW = {"keep_last": 1, RELIABLE: 1, BEST_EFFORT: 2, "volatile": 2, "automatic": 1}


@dataclass(frozen=True)
class TopicSpec:
    key: str
    name: str  # the ROS 2 topic name, e.g. /cellbridge/tactile_state
    ros_type: str  # e.g. tactile_msgs/msg/TactileState
    reliability: str
    depth: int

    @property
    def message_class(self) -> type:
        """Its class in :mod:`cellbridge.ros2.types` (imported here: it needs Cyclone DDS)."""
        from cellbridge.ros2.types import ALL

        return ALL[self.ros_type]

    @property
    def dds_name(self) -> str:
        """The DDS topic name ROS 2 uses for it: ``rt`` + the topic name."""
        return "rt" + self.name

    def offered_qos_yaml(self) -> str:
        """rosbag2's ``offered_qos_profiles`` text of this topic (one profile, rmw enum values)."""
        return (f"- history: {_RMW['keep_last']}\n  depth: {self.depth}\n  reliability: {_RMW[self.reliability]}\n"
                f"  durability: {_RMW['volatile']}\n  deadline:\n    sec: 0\n    nsec: 0\n  lifespan:\n    sec: 0\n"
                f"    nsec: 0\n  liveliness: {_RMW['automatic']}\n  liveliness_lease_duration:\n    sec: 0\n"
                f"    nsec: 0\n  avoid_ros_namespace_conventions: false")


class BadTopicName(ValueError):
    """A namespace or topic name ROS 2 would not take."""


def check_name(name: str) -> str:
    """``name`` if it is a valid absolute ROS 2 topic name (``/a/b_c``), else BadTopicName."""
    if not re.fullmatch(r"(/[A-Za-z][A-Za-z0-9_]*)+", name) or "__" in name:
        raise BadTopicName(f"{name!r} is not an absolute ROS 2 name (/word/word..., letters, digits, "
                           "single underscores, each part starting with a letter)")
    return name


def topics(namespace: str = "/cellbridge", diagnostics: str = "/diagnostics") -> dict[str, TopicSpec]:
    """The topics under ``namespace`` (BadTopicName for a name ROS 2 would refuse)."""
    ns = check_name(namespace.rstrip("/"))
    check_name(diagnostics)
    return {
        "state": TopicSpec("state", f"{ns}/tactile_state", "tactile_msgs/msg/TactileState", BEST_EFFORT, 5),
        "contacts": TopicSpec("contacts", f"{ns}/contacts", "tactile_msgs/msg/TactileContacts", RELIABLE, 10),
        "markers": TopicSpec("markers", f"{ns}/markers", "visualization_msgs/msg/MarkerArray", RELIABLE, 10),
        "diagnostics": TopicSpec("diagnostics", diagnostics, "diagnostic_msgs/msg/DiagnosticArray", RELIABLE, 10),
    }
