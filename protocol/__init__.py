"""Wire protocol of the cell-bridge network, sans-I/O.

Nothing here touches sockets, serial ports, asyncio or clocks: callers feed bytes
(and, for reassembly, the current time) and get frames back, so the same code runs
in bridge emulators, in virtual-time simulations and in the host daemon.
``docs/protocol.md`` is the specification.
"""

from cellbridge.protocol.copies import RecentFrames
from cellbridge.protocol.crc import CRC_CHECK, crc16
from cellbridge.protocol.dedupe import DuplicateFilter
from cellbridge.protocol.errors import ProtocolError
from cellbridge.protocol.fragment import Reassembler, fragment
from cellbridge.protocol.frame import (
    ADDR_BROADCAST,
    ADDR_HOST,
    CRC_LEN,
    HEADER_LEN,
    MAX_DATAGRAM,
    MAX_FRAME,
    MIN_FRAME,
    VERSION,
    Flags,
    Fragment,
    Frame,
    decode,
    encode,
)
from cellbridge.protocol.host import HostReceiver
from cellbridge.protocol.messages import (
    Beacon,
    BridgeStatus,
    Bundle,
    Command,
    CommandReply,
    Data,
    FrameType,
    Hello,
    LinkAck,
    MeshTime,
    Message,
    Mode,
    Neighbour,
    Op,
    Readout,
    ReadoutSame,
    ReadoutSample,
    Sample,
    SampleFlags,
    Status,
    unpack_payload,
)
from cellbridge.protocol.relay import Raw, addressed_to, own, peek, reframe, to_serial
from cellbridge.protocol.stream import StreamDecoder, encode_stream

__all__ = [
    "ADDR_BROADCAST", "ADDR_HOST", "CRC_LEN", "HEADER_LEN", "MAX_DATAGRAM", "MAX_FRAME", "MIN_FRAME", "VERSION",
    "CRC_CHECK",
    "Beacon", "BridgeStatus", "Bundle", "Command", "CommandReply", "Data", "DuplicateFilter",
    "Flags", "Fragment", "Frame", "FrameType", "Hello", "HostReceiver", "LinkAck", "MeshTime", "Message", "Mode",
    "Neighbour", "Op", "ProtocolError", "Readout", "ReadoutSame", "ReadoutSample", "Reassembler", "RecentFrames", "Sample", "SampleFlags", "Status",
    "Raw", "StreamDecoder", "addressed_to", "crc16", "decode", "encode", "encode_stream", "fragment", "own",
    "peek", "reframe", "to_serial", "unpack_payload",
]
