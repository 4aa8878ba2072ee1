"""`cellbridge keys gen` (the installed command): a usable key pair, the secret 0600 from the start."""

from __future__ import annotations

import os
import stat
import subprocess
from pathlib import Path

import zmq
from cellbridge.daemon.ops.security import load_curve
from cellbridge.daemon.shell.keys import write_keypair
from zmq.auth import load_certificate

from daemon_harness import CLI


def keys_gen(*args: str, umask: int = 0o022) -> subprocess.CompletedProcess[str]:
    return subprocess.run([CLI, "keys", "gen", *args], capture_output=True, text=True, timeout=60,
                          preexec_fn=lambda: os.umask(umask))


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_gen_writes_a_matching_pair_with_a_private_secret(tmp_path: Path) -> None:
    out = keys_gen("--dir", str(tmp_path), "server", umask=0)  # even a permissive umask leaves the secret private
    assert out.returncode == 0, out.stderr
    public_file, secret_file = tmp_path / "server.key", tmp_path / "server.key_secret"
    assert mode(secret_file) == 0o600 and mode(public_file) == 0o644
    public, no_secret = load_certificate(public_file)
    public_again, secret = load_certificate(secret_file)
    assert no_secret is None and public == public_again
    assert secret is not None and zmq.curve_public(secret) == public  # a real pair, not two random keys
    assert public.decode() in out.stdout
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary file left behind


def test_generated_files_configure_the_daemon(tmp_path: Path) -> None:
    (tmp_path / "clients").mkdir()
    assert keys_gen("--dir", str(tmp_path)).returncode == 0  # default name: server
    assert keys_gen("--dir", str(tmp_path / "clients"), "arm").returncode == 0
    curve = load_curve({"server_secret_file": "server.key_secret", "allowed_clients_dir": "clients"}, base_dir=tmp_path)
    assert curve is not None


def test_gen_refuses_to_overwrite_unless_forced(tmp_path: Path) -> None:
    write_keypair(tmp_path, "server")
    before = (tmp_path / "server.key_secret").read_bytes()
    again = keys_gen("--dir", str(tmp_path))
    assert again.returncode == 2 and "exists (use --force" in again.stderr
    assert (tmp_path / "server.key_secret").read_bytes() == before
    forced = keys_gen("--dir", str(tmp_path), "--force")
    assert forced.returncode == 0 and (tmp_path / "server.key_secret").read_bytes() != before
    assert mode(tmp_path / "server.key_secret") == 0o600


def test_gen_bad_input_gives_clear_errors(tmp_path: Path) -> None:
    bad_name = keys_gen("--dir", str(tmp_path), "../escape")
    assert bad_name.returncode == 2 and "plain file name" in bad_name.stderr
    (tmp_path / "a-file").write_text("")
    no_dir = keys_gen("--dir", str(tmp_path / "a-file" / "keys"))  # a folder that cannot be made
    assert no_dir.returncode == 2 and "cannot make" in no_dir.stderr and "a-file" in no_dir.stderr, no_dir.stderr
    assert "Traceback" not in bad_name.stderr + no_dir.stderr


def test_gen_makes_a_missing_folder_private(tmp_path: Path) -> None:
    # `keys gen --dir DIR` refused a DIR that was not there, where `mesh up --pty-link DIR` and
    # `robot run --out DIR` make theirs; now it makes it (and its missing parents), 0700 whatever
    # the umask: a folder of secret keys is its owner's alone
    target = tmp_path / "etc" / "cellbridge"
    out = keys_gen("--dir", str(target), "server", umask=0)
    assert out.returncode == 0, out.stderr
    assert (target / "server.key").is_file() and mode(target / "server.key_secret") == 0o600
    assert mode(target) == 0o700 and mode(tmp_path / "etc") == 0o700
    assert f"made {target}" in out.stdout or f"made {target}" in out.stderr, (out.stdout, out.stderr)
    os.chmod(target, 0o755)  # a folder that is there keeps its mode
    assert keys_gen("--dir", str(target), "arm").returncode == 0 and mode(target) == 0o755
    help_text = subprocess.run([CLI, "keys", "gen", "--help"], capture_output=True, text=True, timeout=60).stdout
    assert "made if missing" in " ".join(help_text.split())
