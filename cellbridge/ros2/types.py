"""The ROS 2 messages we publish, as DDS types: one class per ``.msg`` of ``interfaces/``.

Each class is a Cyclone DDS ``IdlStruct`` with the type name ROS 2 gives the message on
DDS (``package::msg::dds_::Name_``), its fields in the order and of the types the
``.msg`` says (``tests/test_ros2_messages.py`` checks them against the ``.msg`` files
through another parser). The same objects are written on the ROS 2 graph
(:mod:`cellbridge.ros2.graph`) and serialised into bags (:func:`cdr`): plain CDR
(XCDR1), little endian, with its 4-byte encapsulation header, which is what ROS 2's
middlewares put on the wire and rosbag2 stores.

Every field has a default (zero, empty), as a ROS 2 message does. (No ``from __future__ import
annotations`` here: Cyclone DDS reads the annotations as objects.)
"""


from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from cyclonedds.idl import IdlStruct
from cyclonedds.idl._support import Endianness
from cyclonedds.idl.types import byte, float32, float64, int32, uint8, uint32

if TYPE_CHECKING:  # to a type checker an IDL sequence is the list it holds
    from builtins import list as sequence
else:
    from cyclonedds.idl.types import sequence


def _dds(name: str) -> str:
    """``std_msgs/Header`` -> ``std_msgs::msg::dds_::Header_``."""
    pkg, msg = name.split("/")
    return f"{pkg}::msg::dds_::{msg}_"


# ---- builtin_interfaces, std_msgs ---------------------------------------------------------------

@dataclass
class Time(IdlStruct, typename=_dds("builtin_interfaces/Time")):
    ROS = "builtin_interfaces/msg/Time"
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Duration(IdlStruct, typename=_dds("builtin_interfaces/Duration")):
    ROS = "builtin_interfaces/msg/Duration"
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Header(IdlStruct, typename=_dds("std_msgs/Header")):
    ROS = "std_msgs/msg/Header"
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class ColorRGBA(IdlStruct, typename=_dds("std_msgs/ColorRGBA")):
    ROS = "std_msgs/msg/ColorRGBA"
    r: float32 = 0.0
    g: float32 = 0.0
    b: float32 = 0.0
    a: float32 = 0.0


# ---- geometry_msgs, sensor_msgs -----------------------------------------------------------------

@dataclass
class Point(IdlStruct, typename=_dds("geometry_msgs/Point")):
    ROS = "geometry_msgs/msg/Point"
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Vector3(IdlStruct, typename=_dds("geometry_msgs/Vector3")):
    ROS = "geometry_msgs/msg/Vector3"
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename=_dds("geometry_msgs/Quaternion")):
    ROS = "geometry_msgs/msg/Quaternion"
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class Pose(IdlStruct, typename=_dds("geometry_msgs/Pose")):
    ROS = "geometry_msgs/msg/Pose"
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class Wrench(IdlStruct, typename=_dds("geometry_msgs/Wrench")):
    ROS = "geometry_msgs/msg/Wrench"
    force: Vector3 = field(default_factory=Vector3)
    torque: Vector3 = field(default_factory=Vector3)


@dataclass
class ChannelFloat32(IdlStruct, typename=_dds("sensor_msgs/ChannelFloat32")):
    ROS = "sensor_msgs/msg/ChannelFloat32"
    name: str = ""
    values: sequence[float32] = field(default_factory=list)


@dataclass
class CompressedImage(IdlStruct, typename=_dds("sensor_msgs/CompressedImage")):
    ROS = "sensor_msgs/msg/CompressedImage"
    header: Header = field(default_factory=Header)
    format: str = ""
    data: sequence[uint8] = field(default_factory=list)


# ---- tactile_msgs -------------------------------------------------------------------------------

@dataclass
class TactileState(IdlStruct, typename=_dds("tactile_msgs/TactileState")):
    ROS = "tactile_msgs/msg/TactileState"
    header: Header = field(default_factory=Header)
    sensors: sequence[ChannelFloat32] = field(default_factory=list)


@dataclass
class TactileContact(IdlStruct, typename=_dds("tactile_msgs/TactileContact")):
    ROS = "tactile_msgs/msg/TactileContact"
    header: Header = field(default_factory=Header)
    name: str = ""
    position: Point = field(default_factory=Point)
    normal: Vector3 = field(default_factory=Vector3)
    wrench: Wrench = field(default_factory=Wrench)


@dataclass
class TactileContacts(IdlStruct, typename=_dds("tactile_msgs/TactileContacts")):
    ROS = "tactile_msgs/msg/TactileContacts"
    contacts: sequence[TactileContact] = field(default_factory=list)


# ---- diagnostic_msgs ----------------------------------------------------------------------------

@dataclass
class KeyValue(IdlStruct, typename=_dds("diagnostic_msgs/KeyValue")):
    ROS = "diagnostic_msgs/msg/KeyValue"
    key: str = ""
    value: str = ""


@dataclass
class DiagnosticStatus(IdlStruct, typename=_dds("diagnostic_msgs/DiagnosticStatus")):
    ROS = "diagnostic_msgs/msg/DiagnosticStatus"
    OK = 0
    WARN = 1
    ERROR = 2
    STALE = 3
    level: byte = 0
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: sequence[KeyValue] = field(default_factory=list)


@dataclass
class DiagnosticArray(IdlStruct, typename=_dds("diagnostic_msgs/DiagnosticArray")):
    ROS = "diagnostic_msgs/msg/DiagnosticArray"
    header: Header = field(default_factory=Header)
    status: sequence[DiagnosticStatus] = field(default_factory=list)


# ---- visualization_msgs -------------------------------------------------------------------------

@dataclass
class UVCoordinate(IdlStruct, typename=_dds("visualization_msgs/UVCoordinate")):
    ROS = "visualization_msgs/msg/UVCoordinate"
    u: float32 = 0.0
    v: float32 = 0.0


@dataclass
class MeshFile(IdlStruct, typename=_dds("visualization_msgs/MeshFile")):
    ROS = "visualization_msgs/msg/MeshFile"
    filename: str = ""
    data: sequence[uint8] = field(default_factory=list)


@dataclass
class Marker(IdlStruct, typename=_dds("visualization_msgs/Marker")):
    ROS = "visualization_msgs/msg/Marker"
    ARROW = 0
    CUBE = 1
    CYLINDER = 3
    CUBE_LIST = 6
    TEXT_VIEW_FACING = 9
    ADD = 0
    DELETEALL = 3
    header: Header = field(default_factory=Header)
    ns: str = ""
    id: int32 = 0
    type: int32 = 0
    action: int32 = 0
    pose: Pose = field(default_factory=Pose)
    scale: Vector3 = field(default_factory=Vector3)
    color: ColorRGBA = field(default_factory=ColorRGBA)
    lifetime: Duration = field(default_factory=Duration)
    frame_locked: bool = False
    points: sequence[Point] = field(default_factory=list)
    colors: sequence[ColorRGBA] = field(default_factory=list)
    texture_resource: str = ""
    texture: CompressedImage = field(default_factory=CompressedImage)
    uv_coordinates: sequence[UVCoordinate] = field(default_factory=list)
    text: str = ""
    mesh_resource: str = ""
    mesh_file: MeshFile = field(default_factory=MeshFile)
    mesh_use_embedded_materials: bool = False


@dataclass
class MarkerArray(IdlStruct, typename=_dds("visualization_msgs/MarkerArray")):
    ROS = "visualization_msgs/msg/MarkerArray"
    markers: sequence[Marker] = field(default_factory=list)


#: Every type above, by its ROS 2 name.
ALL: dict[str, type[IdlStruct]] = {t.ROS: t for t in (
    Time, Duration, Header, ColorRGBA, Point, Vector3, Quaternion, Pose, Wrench, ChannelFloat32, CompressedImage,
    TactileState, TactileContact, TactileContacts, KeyValue, DiagnosticStatus, DiagnosticArray, UVCoordinate,
    MeshFile, Marker, MarkerArray)}


def cdr(message: IdlStruct) -> bytes:
    """The message as ROS 2 serialises it: encapsulation header (CDR, little endian) and
    plain CDR (XCDR1) body."""
    return message.serialize(use_version_2=False, endianness=Endianness.Little)


def stamp(t: float) -> Time:
    """A ``builtin_interfaces/Time`` of ``t`` s since the epoch (0 for a time that is not one,
    or one past what its int32 seconds hold: 2038; the encoder would refuse the message)."""
    if not (t == t) or t <= 0 or t >= 2**31:
        return Time()
    ns = int(round(t * 1e9))
    sec = ns // 1_000_000_000
    if sec >= 2**31:  # rounded up onto 2**31 s
        return Time()
    return Time(sec=sec, nanosec=ns % 1_000_000_000)
