"""SIGTERM to a real daemon whose contact worker hangs: seconds from the signal to its exit.

Run: ``.venv/bin/python bench/bench_stop_hung_worker.py [TREE]`` (TREE: a checkout whose
harness (daemon_harness, daemon_traffic) to use, default this one; the daemon is the ``cellbridge`` beside the
python running this). A 3x3 skin is calibrated and pressed until a contact is
published, then the contact worker process is stopped (SIGSTOP: hung mid-estimate),
an estimate is sent its way, and the daemon gets SIGTERM. The unit's TimeoutStopSec is 15 s.
"""
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

tree = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[1]
sys.path.insert(0, str(tree / "bench"))
from daemon_harness import Client, Pty, daemon, write_config  # noqa: E402
from daemon_traffic import GridFrames  # noqa: E402

with tempfile.TemporaryDirectory() as d:
    tmp = Path(d)
    pty = Pty(tmp / "gw")
    cfg = tmp / "daemon.toml"
    ep = write_config(cfg, [{"name": "gw", "url": pty.link}], calibration={"n_baseline": 10})
    client = Client(ep)
    with daemon(cfg, tmp / "err.log") as proc:
        client.ready() if hasattr(client, "ready") else time.sleep(2)
        sk = GridFrames(rows=3, cols=3)
        pty.write(sk.hellos() + sk.beacons())
        k, ready, end = 0, False, time.monotonic() + 60
        while not ready and time.monotonic() < end:
            pty.write(sk.slot(k))
            k += 1
            got = client.recv(0.005)
            while got is not None and not ready:
                ready = got[0] == "health" and got[1]["layout"]["elements"] == 9 and not got[1]["layout"]["not_ready"]
                got = client.recv(0)
        assert ready
        seen, end = False, time.monotonic() + 60
        while not seen and time.monotonic() < end:
            pty.write(sk.slot(k, (0.020, 0.020, 3.0, 0.012)))
            k += 1
            got = client.recv(0.005)
            while got is not None:
                seen = seen or (got[0] == "contact" and bool(got[1]["contacts"]))
                got = client.recv(0)
        if not seen:
            print(open(tmp / 'err.log').read()[-3000:])
        assert seen
        kids = subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True, text=True).stdout.split()
        for w in kids:
            os.kill(int(w), signal.SIGSTOP)  # the worker hangs
        for _ in range(30):  # an estimate goes to the hung worker
            pty.write(sk.slot(k, (0.020, 0.020, 3.0, 0.012)))
            k += 1
            time.sleep(0.01)
        time.sleep(0.5)
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        try:
            code: int | None = proc.wait(60)
        except subprocess.TimeoutExpired:
            code = None
        took = time.monotonic() - t0
        last = None
        while True:
            got = client.recv(0.2)
            if got is None:
                break
            last = got[0]
        for w in kids:
            try:
                os.kill(int(w), signal.SIGKILL)
            except ProcessLookupError:
                pass
        print(f"workers {kids}; SIGTERM -> exit {code} in {took:.1f} s; last message after it: {last}")
    client.close()
    pty.close()
