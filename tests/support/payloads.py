"""A frame's payload as the kind of message a test expects it to carry, typed.

``Frame.payload`` is any message (or a fragment); a test that reads a DATA frame's samples
knows which it holds. ``payload_as(frame, Data).samples`` says so to the type checker and
checks it: a frame carrying another kind fails the test naming both kinds, where a bare
``frame.payload.samples`` would fail with an AttributeError on whatever it carried.
"""

from __future__ import annotations

from typing import TypeVar

from cellbridge.protocol import Fragment, Frame, Message

M = TypeVar("M", bound=Message | Fragment)


def payload_as(frame: Frame, kind: type[M]) -> M:
    """``frame.payload``, which must be a ``kind`` (AssertionError naming both if not)."""
    found = frame.payload
    if not isinstance(found, kind):
        raise AssertionError(f"a {frame.type.name} frame carries a {type(found).__name__}, not a {kind.__name__}")
    return found
