"""CRC-16 of every frame.

Parameters (CRC-16/CCITT-FALSE, also called CRC-16/IBM-3740): width 16,
polynomial 0x1021, initial value 0xFFFF, no input or output reflection, final
XOR 0x0000; check value over ASCII ``123456789`` is 0x29B1. The CRC is sent
big-endian after the payload. :func:`binascii.crc_hqx` computes exactly this in
C, so no third-party CRC library is needed; the bridge chip computes the same
polynomial bit-serially in a few gates.
"""

from __future__ import annotations

from binascii import crc_hqx

CRC_INIT = 0xFFFF
CRC_POLY = 0x1021
CRC_CHECK = 0x29B1  # crc16(b"123456789")


def crc16(data: bytes | bytearray | memoryview, value: int = CRC_INIT) -> int:
    """CRC-16/CCITT-FALSE of ``data``; pass a previous result as ``value`` to continue."""
    return crc_hqx(data, value)
