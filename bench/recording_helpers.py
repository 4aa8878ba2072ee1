"""Helpers of the recording tests: payload comparison as a subscriber sees it."""

from __future__ import annotations

import math
from typing import Any


def same_payload(a: Any, b: Any) -> bool:
    """Equal as a subscriber sees it: same types (1 is not 1.0), same key order, any NaN
    equals any NaN (the sign and payload bits of a NaN are not kept; they mean nothing)."""
    if type(a) is not type(b) and not (isinstance(a, (list, tuple)) and isinstance(b, (list, tuple))):
        return False
    if isinstance(a, float):
        return (math.isnan(a) and math.isnan(b)) or a == b
    if isinstance(a, dict):
        return list(a) == list(b) and all(same_payload(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(same_payload(x, y) for x, y in zip(a, b))
    return bool(a == b)
