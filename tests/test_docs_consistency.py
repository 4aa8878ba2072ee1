"""The docs say each thing once: no two numbered steps with one number, no field twice in a table."""

from __future__ import annotations

import re
from pathlib import Path

DOCS = Path(__file__).resolve().parent.parent / "docs"


def _tables(text: str) -> list[list[str]]:
    """First cells of every markdown table's rows, one list per table."""
    tables, current = [], []
    for line in text.splitlines():
        if line.startswith("|") and not re.match(r"^\|[\s:-]+\|", line):
            current.append(line.split("|")[1].strip())
        elif current:
            tables.append(current)
            current = []
    if current:
        tables.append(current)
    return tables


def test_no_field_is_described_twice_in_one_table() -> None:
    for doc in sorted(DOCS.glob("*.md")):
        for table in _tables(doc.read_text()):
            dup = sorted({c for c in table[1:] if c and table[1:].count(c) > 1})
            assert not dup, f"{doc.name}: {dup} described twice in one table"


def test_numbered_steps_are_numbered_once() -> None:
    for doc in sorted(DOCS.glob("*.md")):
        seen: list[str] = []
        for line in doc.read_text().splitlines():
            m = re.match(r"^(\d+)\. ", line)
            if m:
                if seen and int(m.group(1)) <= int(seen[-1]) and m.group(1) != "1":
                    raise AssertionError(f"{doc.name}: step {m.group(1)} after step {seen[-1]}: {line[:60]!r}")
                seen = [] if m.group(1) == "1" else seen
                seen.append(m.group(1))
            elif line.startswith("#"):
                seen = []


def test_real_hardware_is_named_by_its_stable_path() -> None:
    """/dev/ttyUSB0 and /dev/pts/N change with plugging order and restarts; users of real
    hardware are told to use /dev/serial/by-id/."""
    text = (DOCS / "daemon.md").read_text()
    assert "/dev/serial/by-id/" in text
