"""``cellbridge plot response``: writes a real PNG, teaches in --help, fails clearly."""

from __future__ import annotations

import struct
import subprocess
import sys

import pytest

from cellbridge.cli import main

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_size(data: bytes) -> tuple[int, int]:
    # The IHDR chunk follows the signature: length, b"IHDR", width, height.
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def test_response_writes_png(tmp_path, capsys):
    out = tmp_path / "response.png"
    rc = main(["plot", "response", "-o", str(out), "--dpi", "60", "--force-range", "0", "10"])
    assert rc == 0
    data = out.read_bytes()
    assert data.startswith(PNG_SIGNATURE)
    w, h = png_size(data)
    assert w > 400 and h > 200
    assert len(data) > 20_000  # a figure, not an empty canvas
    assert str(out) in capsys.readouterr().out


def test_help_teaches(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["plot", "response", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for needle in ("Fig. 2", "--force-range", "10, 16, 20, 26, 30, 40", "0-20 N", "ambiguous",
                   "-o FILE.png"):
        assert needle in text


def test_plot_lists_figures_in_top_level_help(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    assert "plot" in capsys.readouterr().out
    assert main(["plot"]) == 2  # no figure named: prints the figure list


@pytest.mark.parametrize(
    "extra,needle",
    [(["--force-range", "5", "1"], "FMIN < FMAX"), (["--diameters", "50"], "45.1"),
     (["--noise", "-1"], "noise")],
)
def test_bad_options(tmp_path, capsys, extra, needle):
    out = tmp_path / "x.png"
    assert main(["plot", "response", "-o", str(out), *extra]) == 2
    assert needle in capsys.readouterr().err
    assert not out.exists()


def test_missing_matplotlib_is_explained(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib → ImportError
    out = tmp_path / "x.png"
    assert main(["plot", "response", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert "matplotlib" in err and "cellbridge[plot]" in err
    assert not out.exists()


def test_unwritable_output(tmp_path, capsys):
    out = tmp_path / "no-such-dir" / "x.png"
    assert main(["plot", "response", "-o", str(out), "--dpi", "30"]) == 1
    err = capsys.readouterr().err
    # one sentence, the file named once: not the exception's text after it ("[Errno 2] ...: '...x.png'")
    assert err == f"cellbridge plot response: cannot write {out}: No such file or directory\n", err


def test_module_entry_point_help():
    r = subprocess.run([sys.executable, "-m", "cellbridge", "plot", "response", "--help"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "Fig. 2" in r.stdout


def test_response_help_prints_the_noise_default_as_a_number_people_write(capsys):
    """`plot response --help` said '(default: 0.7000000000000001, ...)', the float of 7e-16 F
    in fF: the default is printed as 0.7."""
    with pytest.raises(SystemExit):
        main(["plot", "response", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "(default: 0.7, about two counter counts" in text and "0.7000" not in text
