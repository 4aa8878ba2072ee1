"""The golden corpus (tests/data/golden/): the daemon's pipeline on each recording's serial
channel gives the committed line-per-message output (see tests/support/golden_corpus.py)."""

from __future__ import annotations

import pytest

from support.golden_corpus import SCENARIOS, Scenario, daemon_output, diff, paths

REGEN = "the daemon's output changed: if on purpose, run `.venv/bin/python tests/support/golden_corpus.py --regen` " \
        "and commit the reviewed `git diff tests/data/golden`"


@pytest.mark.parametrize("scenario", SCENARIOS, ids=[sc.name for sc in SCENARIOS])
def test_the_daemon_gives_the_committed_output_on_each_golden_recording(scenario: Scenario) -> None:
    got = daemon_output(scenario, paths(scenario)[0])
    d = diff(scenario, got)
    assert not d, REGEN + "\n" + "\n".join(d[:80])


def test_the_corpus_exercises_what_it_is_made_of() -> None:
    """Each recording shows what its note says: a check of the corpus, not of the daemon."""
    out = {sc.name: daemon_output(sc, paths(sc)[0]) for sc in SCENARIOS}
    health = {name: lines[-1] for name, lines in out.items()}
    assert all(h.startswith("health") for h in health.values())
    assert "gw1:" in health["two_gateways"] and "gw9:" in health["two_gateways"]
    assert "reassembly_completed=0" not in health["fragments"]
    assert "b5:frames" in health["bridge_reset"] and "restarts=1" in health["bridge_reset"]
    assert "framing=0" not in health["line_noise"]
    assert "framing=0" not in health["daemon_press"]  # its line noise and truncated frame
    assert any(" F=" in ln and "touched=1" in ln for ln in out["adc_mode"])
    for name, lines in out.items():  # every recording has its press come out as a contact
        assert any(ln.startswith("contact") and "valid=1" in ln for ln in lines), name


def test_a_changed_output_shows_as_a_readable_diff() -> None:
    sc = SCENARIOS[0]
    got = daemon_output(sc, paths(sc)[0])
    i = next(i for i, ln in enumerate(got) if ln.startswith("contact") and "F=" in ln)
    changed = got[:i] + [got[i].replace("F=", "F=1")] + got[i + 1:]
    d = diff(sc, changed)
    assert [ln[0] for ln in d if ln[:1] in "+-" and ln[:3] not in ("+++", "---")] == ["-", "+"]


def test_the_recordings_are_data_of_protocol_versions_up_to_3_read_through_the_fallback() -> None:
    """The mesh recordings were made before the readout schedule: every frame is of version 3
    or older and none is a READOUT record, so each replay runs the DATA fallback alone (and its
    press still comes out as a contact, above). (The capture scenario's frames are hand-crafted
    DATA of today's version.)"""
    from cellbridge.protocol import FrameType
    from cobs import cobs

    from support.golden_corpus import serial_reads

    for sc in (s for s in SCENARIOS if s.capture is None):
        versions, types = set(), set()
        for _, _, data in serial_reads(paths(sc)[0]):
            for piece in data.split(b"\x00"):
                try:
                    raw = cobs.decode(piece)
                except cobs.DecodeError:  # (a piece split across reads, or line noise)
                    continue
                if len(raw) > 2:
                    versions.add(raw[0])
                    types.add(raw[2])
        assert versions and max(versions) <= 3, (sc.name, versions)
        assert int(FrameType.READOUT) not in types and int(FrameType.DATA) in types, sc.name
