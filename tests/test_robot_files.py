"""``cellbridge robot score DIR`` and ``robot run``'s options, fed what a user gets wrong and
what a hostile file holds: every file it cannot score is refused with the file and line
named and no traceback; files of two runs are refused; a run's files are written whole or
said partial; options out of range are refused before the run (cellbridge/robot_files.py,
cellbridge/robot.py). In process, but for the signal and disk-full tests."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest

from cellbridge.cli import main

ROOT = Path(__file__).resolve().parent.parent


def _truth(start: float = 1.0, link: str = "torso", n: int = 101) -> dict[str, Any]:
    from cellbridge.emulator.world.robot_world import arm_skin

    (sp,) = arm_skin().locate([0.08], [0.06])
    return {"finger": 0, "link": link, "kind": "single", "area": 3e-4, "pad": 0.02, "start": start,
            "end": start + 0.001 * (n - 1),
            "t": [start + 0.001 * k for k in range(n)], "point": [list(sp.position)] * n,
            "normal": [list(sp.normal)] * n, "force": [2.0] * n, "atlas": [[0.08, 0.06]] * n}


def _contact(cid: Any = 1, **kw: Any) -> dict[str, Any]:
    t = _truth()
    return dict({"id": cid, "missed": 0, "link": "torso", "position": t["point"][0], "force": 2.0, "valid": True}, **kw)


def _dir(tmp_path: Path, truth_lines: list[str], contact_lines: list[str]) -> Path:
    d = tmp_path / "run"
    d.mkdir(exist_ok=True)
    (d / "truth.jsonl").write_text("".join(line + "\n" for line in truth_lines))
    (d / "contacts.jsonl").write_text("".join(line + "\n" for line in contact_lines))
    return d


def _score(capsys: pytest.CaptureFixture[str], d: Path) -> tuple[int, str, str]:
    rc = main(["robot", "score", str(d)])
    out, err = capsys.readouterr()
    return rc, out, err


GOOD_TRUTH = json.dumps(_truth())
GOOD_FRAME = json.dumps({"t": 1.05, "contacts": [_contact()]})


def test_a_good_pair_scores(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, err = _score(capsys, _dir(tmp_path, [GOOD_TRUTH], [GOOD_FRAME]))
    assert rc == 0 and "detected" in out and "100.0 %" in out, err


@pytest.mark.parametrize("which, line, says", [
    ("contacts", json.dumps({"t": 1.05, "contacts": [_contact("x")]}), "'id' is not an integer"),
    ("contacts", json.dumps({"t": "soon", "contacts": []}), "'t' is not a finite number"),
    ("contacts", json.dumps({"t": 1.05, "contacts": 5}), "'contacts' is not a list"),
    ("contacts", json.dumps({"t": 1.05, "contacts": [_contact(position=[float("nan"), 0, 0])]}),
     "'position' is not 3 finite numbers"),
    ("contacts", json.dumps({"t": float("inf"), "contacts": []}), "'t' is not a finite number"),
    ("contacts", json.dumps([1, 2]), "not a JSON object"),
    ("contacts", json.dumps({"t": 1.05, "contacts": [_contact(cov="big")]}), "'cov' is not a 2x2 covariance"),
    ("truth", json.dumps({k: v for k, v in _truth().items() if k != "kind"}), "'kind' is not a name"),
    ("truth", json.dumps(dict(_truth(), force=[2.0] * 5)), "'force' is not a list as long as 't'"),
    ("truth", json.dumps(dict(_truth(), start=float("nan"))), "'start' is not a finite number"),
    ("truth", json.dumps(dict(_truth(), point=[[0, 0]] * 101)), "'point' holds a value that is not 3 finite"),
    ("truth", GOOD_TRUTH[: len(GOOD_TRUTH) // 2], "not JSON"),
])
def test_a_line_it_cannot_score_is_refused_naming_file_and_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], which: str, line: str, says: str) -> None:
    truths, frames = [GOOD_TRUTH], [GOOD_FRAME]
    (truths if which == "truth" else frames).append(line)
    rc, out, err = _score(capsys, _dir(tmp_path, truths, frames))
    assert rc == 2 and out == "", out
    assert f"{which}.jsonl:2:" in err and says in err, err
    assert "Traceback" not in err


def test_a_truncated_binary_or_empty_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    d = _dir(tmp_path, [GOOD_TRUTH], [GOOD_FRAME])
    (d / "contacts.jsonl").write_bytes(GOOD_FRAME.encode() + b"\n" + GOOD_FRAME.encode()[:40])  # cut short
    rc, _, err = _score(capsys, d)
    assert rc == 2 and "contacts.jsonl:2:" in err and "cut short" in err, err
    (d / "contacts.jsonl").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe\x00")
    rc, _, err = _score(capsys, d)
    assert rc == 2 and "contacts.jsonl:1:" in err and "not UTF-8" in err, err
    (d / "contacts.jsonl").write_text(GOOD_FRAME + "\n")
    (d / "truth.jsonl").write_text("")
    rc, _, err = _score(capsys, d)
    assert rc == 2 and "truth.jsonl" in err and "no true contact" in err, err
    rc, _, err = _score(capsys, tmp_path / "nowhere")
    assert rc == 2 and "no such directory" in err, err


def test_an_overlong_line_is_refused_before_it_is_read(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    import cellbridge.robot_files as rf

    monkeypatch.setattr(rf, "MAX_LINE", 4096)  # a 1 GB line is refused the same way at 64 MiB
    rc, _, err = _score(capsys, _dir(tmp_path, [GOOD_TRUTH], [GOOD_FRAME]))
    assert rc == 2 and "truth.jsonl:1:" in err and "longer than" in err, err


def test_a_cellbridge_sub_recording_is_read_its_other_topics_counted(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    frame = json.loads(GOOD_FRAME)
    lines = [json.dumps({"topic": "health", "payload": {}}),
             json.dumps({"topic": "contact", "payload": {"t_sample": frame["t"], "contacts": frame["contacts"]}})]
    rc, out, err = _score(capsys, _dir(tmp_path, [GOOD_TRUTH], lines))
    assert rc == 0 and "100.0 %" in out and "1 lines of other topics skipped" in out, (out, err)


def test_files_of_two_runs_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from cellbridge.robot_files import write_run

    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    write_run(str(a), [_truth()], [(1.05, [_contact()])], {"seed": 0, "complete": True})
    write_run(str(b), [_truth(start=5.0)], [(5.05, [_contact()])], {"seed": 1, "complete": True})
    rc, out, err = _score(capsys, a)
    assert rc == 0 and "100.0 %" in out and "not checked" not in out, (out, err)
    (a / "contacts.jsonl").write_bytes((b / "contacts.jsonl").read_bytes())
    rc, out, err = _score(capsys, a)
    assert rc == 2 and "contacts.jsonl: not the file this run wrote" in err and "two runs" in err, err
    os.remove(a / "run.json")  # without run.json: b's frames lie outside a's truths' time
    rc, out, err = _score(capsys, a)
    assert rc == 2 and "no frame within the true contacts' time" in err, (out, err)
    (b / "run.json").unlink()  # b's own files without run.json: scored, and said unchecked
    rc, out, err = _score(capsys, b)
    assert rc == 0 and "100.0 %" in out and "not checked" in out, out


def test_a_partial_run_scores_only_what_it_ran(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from cellbridge.robot_files import write_run

    write_run(str(tmp_path), [_truth(), _truth(start=9.0)], [(1.05, [_contact()])],
              {"seed": 0, "complete": False, "until": 4.0})
    rc, out, err = _score(capsys, tmp_path)
    assert rc == 0 and "100.0 %" in out and "partial run" in out and "1 true contacts after it left out" in out, out


@pytest.mark.parametrize("option, says", [
    (["--contacts", "0"], "--contacts must be within 1..10000"),
    (["--contacts", "1000000000"], "--contacts must be within 1..10000"),
    (["--idle", "nan"], "--idle must be within"),
    (["--idle", "inf"], "--idle must be within"),
    (["--idle", "-5"], "--idle must be within"),
    (["--reporting", "bogus"], "--reporting: expected 'periodic'"),
    (["--force"], "--force replaces an earlier run's files in --out DIR: it goes with --out"),
])
@pytest.mark.process  # importing mujoco starts a process
def test_run_options_out_of_range_are_refused_before_the_run(
        capsys: pytest.CaptureFixture[str], option: list[str], says: str) -> None:
    pytest.importorskip("mujoco")
    rc = main(["robot", "run", *option])
    out, err = capsys.readouterr()
    assert rc == 2 and says in err and "Traceback" not in err, err


@pytest.mark.process  # importing mujoco starts a process
def test_an_out_it_cannot_write_is_refused_before_the_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("mujoco")
    (tmp_path / "afile").write_text("x")
    rc = main(["robot", "run", "--contacts", "1", "--out", str(tmp_path / "afile")])
    _, err = capsys.readouterr()
    assert rc == 2 and "exists and is not a directory" in err, err
    rc = main(["robot", "run", "--contacts", "1", "--out", str(tmp_path / "afile" / "sub")])
    _, err = capsys.readouterr()
    assert rc == 2 and "cannot make it" in err, err
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        rc = main(["robot", "run", "--contacts", "1", "--out", str(ro)])
        _, err = capsys.readouterr()
        assert rc == 2 and "cannot write in it" in err, err


@pytest.mark.process  # importing mujoco starts a process
def test_an_out_holding_an_earlier_run_is_refused_before_the_run_unless_force(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # A second `robot run --out run/` replaced the first run's files without a word (an
    # hour's run lost to a repeated command line); `keys gen` and a ROS 2 bag refuse an
    # existing file, `keys gen --force` replaces it.
    from cellbridge.robot_files import RunFileError, prepare_out

    pytest.importorskip("mujoco")
    d = _dir(tmp_path, [GOOD_TRUTH], [GOOD_FRAME])
    (d / "run.json").write_text("{}\n")
    before = {p.name: p.read_bytes() for p in d.iterdir()}
    with pytest.raises(RunFileError, match="an earlier run"):
        prepare_out(str(d))
    rc = main(["robot", "run", "--contacts", "1", "--out", str(d)])
    _, err = capsys.readouterr()
    assert rc == 2 and "--force" in err and "contacts.jsonl" in err and "Traceback" not in err, err
    assert {p.name: p.read_bytes() for p in d.iterdir()} == before  # nothing of it touched
    prepare_out(str(d), force=True)  # --force: the run may replace them
    (tmp_path / "fresh").mkdir()
    prepare_out(str(tmp_path / "fresh"))  # an empty directory, or one of other files, is no earlier run
    (tmp_path / "fresh" / "notes.txt").write_text("mine")
    prepare_out(str(tmp_path / "fresh"))


@pytest.mark.process
@pytest.mark.timeout(120)
def test_a_full_disk_leaves_no_file_that_looks_whole(tmp_path: Path) -> None:
    """A file-size limit stands in for a full disk: the write fails, no file of the run is
    left (no .partial, no truth.jsonl) and the error is raised to the caller."""
    code = textwrap.dedent(f"""
        import resource, signal, sys
        sys.path.insert(0, {str(ROOT / 'tests')!r})
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (20000, 20000))
        from cellbridge.robot_files import write_run
        from test_robot_files import _truth, _contact
        try:
            write_run({str(tmp_path)!r}, [_truth()] * 3, [(1.0, [_contact()])] * 3, {{"complete": True}})
        except OSError as exc:
            print("raised", exc.errno)
    """)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=100, cwd=ROOT)
    assert "raised" in r.stdout, r.stderr
    assert sorted(os.listdir(tmp_path)) == [], os.listdir(tmp_path)


@pytest.mark.process
@pytest.mark.timeout(300)
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_run_stopped_midway_says_partial_and_leaves_no_process(tmp_path: Path, sig: int) -> None:
    pytest.importorskip("mujoco")
    out = tmp_path / "out"
    p = subprocess.Popen([sys.executable, "-m", "cellbridge", "robot", "run", "--contacts", "2", "--out", str(out)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True, cwd=ROOT)
    try:
        assert p.stderr is not None
        buf = ""
        while "virtual" not in buf:  # the skin and the daemon are running
            ch = p.stderr.read(1)
            assert ch, buf
            buf += ch
        p.send_signal(sig)
        stdout, stderr = p.communicate(timeout=200)
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    assert p.returncode == 130, (stdout, stderr)
    assert "Traceback" not in stderr and "PARTIAL: stopped at virtual" in stdout, (stdout, stderr)
    meta = json.loads((out / "run.json").read_text())
    assert meta["complete"] is False and meta["until"] < meta["virtual_s"]
    with pytest.raises(ProcessLookupError):
        os.killpg(p.pid, 0)  # nothing of its group left


def test_score_says_the_idle_false_contacts_per_ten_minutes_of_idle(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A run with 60 s untouched after its scenario (run.json's busy and idle) and one false
    contact in them: score says so, as a rate over the idle time (10 per 10 minutes), not
    as a bare count to hold against the target's 1 per 10 minutes."""
    from cellbridge.robot_files import write_run

    ghost = _contact(9, position=[0.5, 0.5, 0.5])
    write_run(str(tmp_path), [_truth()], [(1.05, [_contact()]), (30.0, [ghost])],
              {"seed": 0, "complete": True, "until": 63.0, "busy": 3.0, "idle": 60.0, "virtual_s": 63.0})
    rc, out, err = _score(capsys, tmp_path)
    assert rc == 0, err
    assert "idle 60 s: 1 false contacts (10.0 per 10 minutes; target at most 1)" in out, out


@pytest.mark.parametrize("field, value", [("until", "soon"), ("until", [1]), ("complete", "no"), ("busy", float("nan")),
                                          ("until", float("inf"))])
def test_a_run_json_with_mistyped_fields_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                    field: str, value: Any) -> None:
    from cellbridge.robot_files import write_run

    write_run(str(tmp_path), [_truth()], [(1.05, [_contact()])],
              {"seed": 0, "complete": False, "until": 4.0, "busy": 3.0, field: value})
    rc, out, err = _score(capsys, tmp_path)
    assert rc == 2 and "run.json" in err and f"'{field}'" in err and "Traceback" not in err, (out, err)


@pytest.mark.parametrize("change, says", [
    ({"link": "ghost"}, "link 'ghost' is not a link of the arm's skin"),
    ({"atlas": [[1e6, 1e6]] * 101}, "is not on link torso"),
    ({"atlas": [[0.08, 0.06]] * 100 + [[5.0, -3.0]]}, "step 100"),
])
def test_a_true_contact_off_the_arms_skin_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                    change: dict[str, Any], says: str) -> None:
    """A truth on a link the arm has not (files of another skin), or whose atlas place is
    off its link's patches, cannot be matched or placed: it was scored as a miss, or its
    reports' errors measured against a place on no skin."""
    rc, out, err = _score(capsys, _dir(tmp_path, [GOOD_TRUTH, json.dumps(dict(_truth(), **change))], [GOOD_FRAME]))
    assert rc == 2 and "truth.jsonl:2:" in err and says in err, (out, err)


@pytest.mark.process
@pytest.mark.timeout(120)
@pytest.mark.parametrize("action", ["skin", "mjcf", "score"])
def test_a_reader_that_goes_away_ends_the_output_without_a_traceback(tmp_path: Path, action: str) -> None:
    """``cellbridge robot score DIR | head -3``: the reader closes the pipe; that is the end of
    the output, not a BrokenPipeError traceback."""
    d = _dir(tmp_path, [GOOD_TRUTH], [GOOD_FRAME])
    cmd = [sys.executable, "-m", "cellbridge", "robot", action] + ([str(d)] if action == "score" else [])
    r, w = os.pipe()
    os.close(r)  # the reader is gone before the first line
    try:
        p = subprocess.run(cmd, stdout=w, stderr=subprocess.PIPE, text=True, timeout=100, cwd=ROOT)
    finally:
        os.close(w)
    assert "Traceback" not in p.stderr and "BrokenPipe" not in p.stderr, p.stderr
    assert p.returncode == 0, p.stderr


def test_a_sub_recordings_nulls_for_infinite_and_unknown_numbers_are_scored(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``cellbridge sub`` writes a number that is not finite as null: an unobservable axis's
    infinite variance in ``cov``, a force not known. Such a recording is scored (the axis
    unresolved, the force left out), not refused and no TypeError."""
    c = _contact(force=None, observable=[False, True], cov=[[None, 0.0], [0.0, 1e-8]])
    line = json.dumps({"topic": "contact", "payload": {"t_sample": 1.2, "contacts": [c]}})  # held: scored
    rc, out, err = _score(capsys, _dir(tmp_path, [json.dumps(_truth(n=501))], [line]))
    assert rc == 0 and "100.0 %" in out and "Traceback" not in err, (out, err)
    rows = {ln[:52].strip(): ln[52:].split() for ln in out.splitlines()}
    assert rows["reports scored"][0] == "1" and rows["force error, median"][0] == "nan", out


def test_a_fifo_or_a_directory_in_place_of_a_file_is_refused_not_waited_on(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``robot score`` opened a FIFO named truth.jsonl and waited for a writer for ever."""
    d = _dir(tmp_path, [GOOD_TRUTH], [GOOD_FRAME])
    os.remove(d / "truth.jsonl")
    os.mkfifo(d / "truth.jsonl")
    rc, _, err = _score(capsys, d)
    assert rc == 2 and "truth.jsonl" in err and "not a regular file" in err, err


@pytest.mark.process  # importing mujoco starts a process
def test_an_out_whose_file_names_are_taken_by_directories_is_refused_before_the_run(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A directory named contacts.jsonl in --out made the run's last step (the rename) fail,
    after the whole run."""
    pytest.importorskip("mujoco")
    (tmp_path / "contacts.jsonl").mkdir()
    rc = main(["robot", "run", "--contacts", "1", "--out", str(tmp_path)])
    _, err = capsys.readouterr()
    assert rc == 2 and "contacts.jsonl" in err and "not a regular file" in err, err


def test_a_long_runs_frames_keep_only_what_the_scorer_reads(tmp_path: Path) -> None:
    """A published contact carries some thirty fields; robot score kept them all (a 100 MB
    contacts.jsonl took about 500 MB), of which it reads eight. Frames without contacts
    hold nothing to score and are not kept."""
    from cellbridge.robot_files import SCORED, read_frames

    full = _contact(age=12, t=1.0, x=0.1, y=0.2, elements=list(range(40)), cycles=list(range(40)), chi2=1.0)
    p = tmp_path / "contacts.jsonl"
    p.write_text(json.dumps({"t": 1.0, "contacts": [full]}) + "\n" + json.dumps({"t": 1.1, "contacts": []}) + "\n")
    frames, other = read_frames(str(p))
    assert other == 0 and len(frames) == 1
    (c,) = frames[0][1]
    assert set(c) <= set(SCORED) and c["id"] == 1 and c["position"] == full["position"]


def test_contacts_on_another_clock_than_the_truths_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A ``cellbridge sub contact`` recording of a real-time daemon has t_sample on the epoch
    (1.8e9 s), the truth seconds from the run's start: no frame falls within any truth's
    time, and the table said 0 % detected, every contact false, with confidence."""
    frame = json.loads(GOOD_FRAME)
    line = json.dumps({"topic": "contact", "payload": {"t_sample": 1.8e9 + frame["t"], "contacts": frame["contacts"]}})
    rc, out, err = _score(capsys, _dir(tmp_path, [GOOD_TRUTH], [line]))
    assert rc == 2 and "contacts.jsonl" in err and "clock" in err, (out, err)


def test_a_daemon_restarted_in_a_sub_recording_has_its_false_contact_counted_false(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A restarted daemon numbers its contacts from 0 again: in a ``cellbridge sub`` recording
    its new contact 0, touching nothing, took the id of the old process's contact 0 that
    matched the press, and was scored as that detected contact lingering ("reports of
    detected ids while they matched nothing"), the false contacts row reading 0. Each daemon
    run's ids are now told apart (its ``seq`` going back), and a message recorded twice is
    scored once; both are said."""
    far = _contact(0, position=[9.0, 9.0, 9.0])
    lines = [json.dumps({"topic": "contact", "payload": {"seq": s, "source": "arm:5560", "t_sample": t,
                                                          "contacts": cs}})
             for s, t, cs in ((7, 1.05, [_contact(0)]), (7, 1.05, [_contact(0)]),  # the same message twice
                              (0, 1.06, [far]))]  # the daemon restarted: seq from 0, ids from 0
    rc, out, err = _score(capsys, _dir(tmp_path, [GOOD_TRUTH], lines))
    assert rc == 0, err
    rows = {ln[:52].strip(): ln[52:].split() for ln in out.splitlines()}
    assert rows["false contacts (ids matching nothing)"][0] == "1", out
    assert rows["reports of detected ids while they matched nothing"][0] == "0", out
    assert "restarted" in out and "1 message recorded twice" in out, out
