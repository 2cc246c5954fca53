"""Tests of ``controlgs_adapter.commands.optics``: ``build-bank``, ``fit-prewarp``, ``bench`` and ``figures`` (their
defaults, their outputs, the command line a bench page names) and what they refuse in one line before any work
(numbers, prescriptions, outputs in the way, a full disk)."""

from __future__ import annotations

import errno
import json
import re
import shlex
from pathlib import Path
from typing import Any

import pytest
from helpers.banks import tiny_bank
from helpers.cli_runs import error_line

from controlgs_adapter import cli
from controlgs_adapter.cli import main
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.generate import lens_figures
from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription
from controlgs_adapter.errors import FileFormatError

#: a one-size optics bench that runs in seconds
BENCH = ["optics", "bench", "--sizes", "16", "--radiometry", "radiance", "--repeat", "1", "--no-scaling", "--threads", "1"]


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    import controlgs_adapter.downstream.optics.bench as bench
    import controlgs_adapter.downstream.optics.generate as generate
    import controlgs_adapter.downstream.prewarp_fit as prewarp_fit

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the work started")

    monkeypatch.setattr(generate, "build_bank", refuse)
    monkeypatch.setattr(prewarp_fit, "fit_bank_prewarp", refuse)
    monkeypatch.setattr(bench, "run", refuse)


def _page_command(page: Path) -> list[str]:
    """The command line a bench page names, split as a shell would."""
    return shlex.split(page.read_text().split("Command: `", 1)[1].split("`", 1)[0])


# ----------------------------------------------------------------------------- defaults and outputs

def test_optics_defaults() -> None:
    o = cli.build_parser().parse_args(["optics", "build-bank"])
    assert (o.out, tuple(o.grid), o.psf_size, o.pupil_samples, o.min_pitch_px, o.lens) == \
        (Path("psf_bank.safetensors"), (30, 30), 33, 192, 0.125, "cardboard")
    assert cli.build_parser().parse_args(["optics", "figures"]).lens == "cardboard"
    c = cli.build_parser().parse_args(["optics", "bench"])
    assert (c.sizes, c.radiometry, c.tols, c.repeat, c.scaling, c.zone, c.exact_max, c.threads, c.out) == \
        (["256", "512", "1024", "576x1024"], ["radiance", "energy"], [0.02], 3, True, 5, 1024, 2, None)
    assert cli.build_parser().parse_args(["optics", "bench", "--doc"]).out == Path("docs") / "benchmarks"
    assert cli.build_parser().parse_args(["optics", "bench", "--no-scaling"]).scaling is False
    w = cli.build_parser().parse_args(["optics", "fit-prewarp", "--out", "l.safetensors"])
    assert (w.lens, w.size, w.modes, w.radiometry) == ("cardboard", [64, 96, 128, 192, 256], ["distortion", "exact"],
                                                        "radiance")


def test_bench_and_fit_prewarp_write_their_outputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = [*BENCH, "--exact-max", "16", "--out", str(tmp_path / "o b")]
    assert main(argv) == 0
    assert sorted(p.name for p in (tmp_path / "o b").iterdir()) == ["optics_bench.md", "optics_bench.png"]
    # the page names the exact command line, quoted for a shell, so that it can be run again
    assert _page_command(tmp_path / "o b" / "optics_bench.md") == ["controlgs", *argv]
    assert "16x16 radiance exact" in capsys.readouterr().out
    lut = tmp_path / "lut.safetensors"
    assert main(["optics", "fit-prewarp", "--size", "8", "--modes", "distortion", "--radiometry", "energy",
                 "--out", str(lut)]) == 0  # not the default radiometry: the option must reach the fit
    out = capsys.readouterr().out
    meta = json.loads(out[:out.rindex("}") + 1])
    assert (meta["size"], meta["radiometry"], list(meta["residuals"])) == ([8, 8], "energy", ["distortion"])
    assert lut.is_file() and out.strip().splitlines()[-1].startswith(f"wrote {lut} (")


def test_a_bench_page_names_sys_argv_when_main_is_given_none(tmp_path, monkeypatch):
    """As the console script calls it (``main()``), the page names the shell's arguments after the program name."""
    argv = [*BENCH, "--out", str(tmp_path / "b")]
    monkeypatch.setattr("sys.argv", ["/some/bin/controlgs", *argv])
    assert main() == 0
    assert _page_command(tmp_path / "b" / "optics_bench.md") == ["controlgs", *argv]


def test_build_bank_smallest_accepted_values(tmp_path, capsys):
    """The documented lower bounds are inclusive: ``--grid 1 1``, ``--psf-size 5`` (odd >= 5),
    ``--pupil-samples 4`` (>= 4) and a pitch below one pixel build a bank of that shape."""

    out = tmp_path / "b.safetensors"
    assert main(["optics", "build-bank", "--grid", "1", "1", "--psf-size", "5", "--pupil-samples", "4",
                     "--min-pitch-px", "0.5", "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith(f"wrote {out} (")
    bank = PSFBank.load(out)
    assert tuple(bank.psf.shape) == (3, 1, 1, 5, 5)  # three primaries, 1 x 1 field, 5 x 5 samples


def test_optics_figures_prints_json(capsys):
    assert main(["optics", "figures"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["half_width_mm"] == 12.0  # Cardboard: a 24 mm wide display half
    assert figures["px_per_mm_display_at_1024"] == pytest.approx(1024 / 24.0)
    assert main(["optics", "figures", "--lens", "cardboard"]) == 0
    assert json.loads(capsys.readouterr().out) == figures


def test_optics_figures_of_the_compact_lens(capsys):
    """``--lens compact``: the figures of the shipped file's prescription, read here on its own."""
    spec = json.loads((Path(cli.__file__).parent / "data" / "compact_prescription.json").read_text(encoding="utf-8"))
    assert main(["optics", "figures", "--lens", "compact"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures == json.loads(json.dumps(lens_figures(Prescription(spec))))
    assert figures["half_width_mm"] == spec["display_mm"][0] / 2 != 12.0
    assert figures["px_per_mm_display_at_1024"] == pytest.approx(1024 / spec["display_mm"][0])


def test_optics_figures_of_an_asymmetric_lens_file(capsys, tmp_path):
    """A decentred lens: per wavelength the 4 corners' landings ``[x, y]`` and distortions, paraxial figures
    null; mirror-symmetric about x = 0 (the decentre is along y), so the -x and +x corners mirror."""
    spec = {**CARDBOARD, "surfaces": [dict(sf, decenter_mm=[0.0, 0.6]) for sf in CARDBOARD["surfaces"]]}
    (tmp_path / "decentred.json").write_text(json.dumps(spec))
    assert main(["optics", "figures", "--lens", str(tmp_path / "decentred.json")]) == 0
    figures = json.loads(capsys.readouterr().out)
    for lam in ("656nm", "550nm", "486nm"):
        f = figures[lam]
        assert f["efl_mm"] is None and f["paraxial_magnification"] is None
        (x0, y0), (x1, y1), (x2, y2), (x3, y3) = f["corner_landing_px_at_1024"]
        assert (x1, y1, x3, y3) == pytest.approx((-x0, y0, -x2, y2)) and y0 < 0 < y2 and y2 != pytest.approx(-y0)
        assert len(f["corner_distortion_pct"]) == 4


# ----------------------------------------------------------------------------- refusals before any work

@pytest.mark.parametrize("args, message", [
    (["--psf-size", "4"], "--psf-size must be an odd integer >= 5, got 4"),
    (["--psf-size", "3"], "--psf-size must be an odd integer >= 5, got 3"),
    (["--grid", "0", "5"], "--grid GY GX must both be >= 1, got 0 5"),
    (["--grid", "5", "0"], "--grid GY GX must both be >= 1, got 5 0"),
    (["--pupil-samples", "3"], "--pupil-samples must be >= 4, got 3"),
    (["--min-pitch-px", "0"], "--min-pitch-px must be a finite number > 0, got 0.0"),
    (["--min-pitch-px", "inf"], "--min-pitch-px must be a finite number > 0, got inf"),
    (["--min-pitch-px", "nan"], "--min-pitch-px must be a finite number > 0, got nan"),
])
def test_build_bank_refusals(capsys, tmp_path, args, message, no_work):
    assert main(["optics", "build-bank", "--out", f"{tmp_path}/b.safetensors", *args]) == 2
    assert error_line(capsys, "optics") == message
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("args, message", [
    (["--lens", "{d}/none.json"], "--lens {d}/none.json: no such file (nor a shipped lens: cardboard, compact)"),
    (["--lens", "cardbaord"], "--lens cardbaord: no such file (nor a shipped lens: cardboard, compact)"),
    (["--lens", "{d}"], "--lens {d}: not a regular file"),
    (["--lens", "{d}/bad.json"], "--lens {d}/bad.json: not a JSON file: "),
    (["--lens", "{d}/latin1.json"], "--lens {d}/latin1.json: not a JSON file: "),
    (["--lens", "{d}/wrong.json"], "--lens {d}/wrong.json: "),
    (["--lens", "{d}/big.json"], "--lens {d}/big.json: 1048577 bytes, too large"),
    (["--lens", "/proc/self/mem"], "--lens /proc/self/mem: not readable: "),
])
@pytest.mark.parametrize("action", ["build-bank", "figures"])
def test_lens_refusals(capsys, tmp_path, action, args, message, no_work):
    """Both actions refuse a bad ``--lens`` in one line naming it, before any work and writing nothing."""
    if "/proc/self/mem" in args and not Path("/proc/self/mem").is_file():
        pytest.skip("no /proc/self/mem here")
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "latin1.json").write_bytes('{"name": "\xe9"}'.encode("latin-1"))
    (tmp_path / "wrong.json").write_text('{"surfaces": 3}')
    (tmp_path / "big.json").write_bytes(b" " * ((1 << 20) + 1))
    d = str(tmp_path)
    before = sorted(tmp_path.iterdir())
    out = ["--out", f"{d}/b.safetensors"] if action == "build-bank" else []
    assert main(["optics", action, *out, *[a.replace("{d}", d) for a in args]]) == 2
    assert error_line(capsys, "optics").startswith(message.replace("{d}", d))
    assert capsys.readouterr().out == "" and sorted(tmp_path.iterdir()) == before


def test_prescription_is_gone(capsys):
    """``--lens`` is the one way to give a prescription: ``--prescription`` is refused by both actions."""
    for action in ("build-bank", "figures"):
        with pytest.raises(SystemExit) as e:
            main(["optics", action, "--prescription", "rx.json"])
        assert e.value.code == 2 and "unrecognized arguments: --prescription" in capsys.readouterr().err


def test_build_bank_lens_traces_the_shipped_or_given_prescription(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    small = ["--grid", "1", "1", "--psf-size", "5", "--pupil-samples", "4"]
    own = {**CARDBOARD, "object_distance_mm": 38.0}
    (tmp_path / "own.json").write_text(json.dumps(own))
    for name, lens in (("named", "cardboard"), ("file", str(tmp_path / "own.json"))):
        assert main(["optics", "build-bank", "--lens", lens, *small, "--out", str(tmp_path / f"{name}.safetensors")]) == 0
    assert main(["optics", "build-bank", *small, "--out", str(tmp_path / "default.safetensors")]) == 0
    named, file, default = (PSFBank.load(tmp_path / f"{n}.safetensors") for n in ("named", "file", "default"))
    assert named.meta["prescription"] == default.meta["prescription"] == CARDBOARD
    assert file.meta["prescription"] == own and not bool((file.chief == default.chief).all())


def test_fit_prewarp_lens_refusals(tmp_path: Path, capsys: pytest.CaptureFixture[str], no_work: None) -> None:
    """``--lens`` is the one way to name the lens: ``--bank`` is unknown; a bad ``--lens`` is one line naming it,
    exit 2, nothing written."""
    d = tmp_path / "in"
    d.mkdir()
    (d / "junk.safetensors").write_text("junk")
    (d / "lens.txt").write_text("{}")
    lut = tmp_path / "lut.safetensors"
    with pytest.raises(SystemExit) as e:
        main(["optics", "fit-prewarp", "--bank", "b.safetensors", "--out", str(lut)])
    assert e.value.code == 2 and "unrecognized arguments: --bank" in capsys.readouterr().err
    for lens, problem in (("cardbaord", "not a shipped lens (cardboard, compact) nor a file"),
                          (f"{d}/none.safetensors", "no such file"),
                          (f"{d}/junk.safetensors", "not a readable safetensors file"),
                          (f"{d}/lens.txt", "not a lens file")):
        assert main(["optics", "fit-prewarp", "--lens", lens, "--out", str(lut)]) == 2
        assert error_line(capsys, "optics").startswith(f"--lens {lens}: {problem}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


def test_fit_prewarp_fits_through_the_lens_bank(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A bank file given to ``--lens`` is the bank the LUT is fitted for (its fingerprint is in the LUT's meta)."""
    from controlgs_adapter.downstream.bank_maps import bank_fingerprint

    bank, lut = tmp_path / "own.safetensors", tmp_path / "lut.safetensors"
    tiny_bank().save(bank)
    assert main(["optics", "fit-prewarp", "--lens", str(bank), "--size", "8", "--modes", "distortion",
                 "--out", str(lut)]) == 0
    out = capsys.readouterr().out
    assert json.loads(out[:out.rindex("}") + 1])["bank"] == bank_fingerprint(PSFBank.load(bank))


@pytest.mark.parametrize("argv, pattern", [
    (["fit-prewarp", "--size", "9", "--out", "{d}/lut.safetensors"], r"^--size .*got 9$"),
    (["fit-prewarp", "--size", "6", "--out", "{d}/lut.safetensors"], r"^--size .*got 6$"),
    (["bench", "--sizes", "256", "1x4"], r"^--sizes: .*got '1x4'$"),
])
def test_fit_prewarp_and_bench_numbers_are_checked_first(tmp_path: Path, capsys: pytest.CaptureFixture[str], no_work: None,
                                                         argv: list[str], pattern: str) -> None:
    assert main(["optics", *[a.replace("{d}", str(tmp_path)) for a in argv]]) == 2
    assert re.match(pattern, error_line(capsys, "optics"))


@pytest.mark.parametrize("action", [["build-bank"], ["fit-prewarp"]])
def test_a_file_output_under_a_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str], no_work: None,
                                               action: list[str]) -> None:
    blocker = tmp_path / "blocker"
    blocker.write_text("mine")
    out = blocker / "bank.safetensors"
    assert main(["optics", *action, "--out", str(out)]) == 2
    assert error_line(capsys, "optics") == f"--out {out}: {blocker} is a file, not a folder"
    assert main(["optics", *action, "--out", str(tmp_path)]) == 2
    assert error_line(capsys, "optics") == f"--out {tmp_path}: is a folder; expected the path of a file to write"
    assert blocker.read_text() == "mine"


def test_bench_out_that_is_a_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str], no_work: None) -> None:
    taken = tmp_path / "taken"
    taken.write_text("mine")
    assert main(["optics", "bench", "--sizes", "16", "--out", str(taken)]) == 2
    assert error_line(capsys, "optics") == f"--out {taken}: is a file; expected a folder to write into"
    assert taken.read_text() == "mine"


def test_a_full_disk_is_one_line_and_leaves_no_partial_file(tmp_path, capsys, monkeypatch):
    def full(data: Any, tmp: str, metadata: Any = None) -> None:
        Path(tmp).write_bytes(b"half")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("controlgs_adapter.formats.safetensors.save_file", full)
    monkeypatch.setattr("controlgs_adapter.downstream.optics.generate.build_bank", lambda *a, **k: tiny_bank())
    assert main(["optics", "build-bank", "--out", str(tmp_path / "b.safetensors")]) == 2
    line = error_line(capsys, "optics")
    assert "No space left" in line and "b.safetensors" in line
    assert not list(tmp_path.iterdir()), "no partial file left"


# ----------------------------------------------------------------------------- the command line's own errors


# ----------------------------------------------------------------------------- the optics commands
@pytest.fixture
def files(tmp_path):
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "list.json").write_text("[1, 2]")
    (tmp_path / "field.json").write_text(json.dumps({**CARDBOARD, "display_mm": "66"}))
    (tmp_path / "a_file").write_text("x")
    return tmp_path


CLI_CASES = [
    ("psf-size 4", ["optics", "build-bank", "--psf-size", "4"], "--psf-size"),
    ("psf-size 6", ["optics", "build-bank", "--psf-size", "6"], "--psf-size"),
    ("grid 0 0", ["optics", "build-bank", "--grid", "0", "0"], "--grid"),
    ("grid 3 -1", ["optics", "build-bank", "--grid", "3", "-1"], "--grid"),
    ("pupil-samples 1", ["optics", "build-bank", "--pupil-samples", "1"], "--pupil-samples"),
    ("min-pitch-px 0", ["optics", "build-bank", "--min-pitch-px", "0"], "--min-pitch-px"),
    ("min-pitch-px nan", ["optics", "build-bank", "--min-pitch-px", "nan"], "--min-pitch-px"),
    ("prescription missing", ["optics", "build-bank", "--lens", "{d}/none.json"], "none.json"),
    ("prescription not JSON", ["optics", "build-bank", "--lens", "{d}/bad.json"], "bad.json"),
    ("prescription a list", ["optics", "build-bank", "--lens", "{d}/list.json"], "list.json"),
    ("prescription bad field", ["optics", "build-bank", "--lens", "{d}/field.json"], "display_mm"),
    ("out a folder", ["optics", "build-bank", "--out", "{d}"], "--out"),
    ("figures prescription missing", ["optics", "figures", "--lens", "{d}/none.json"], "none.json"),
    ("figures prescription a list", ["optics", "figures", "--lens", "{d}/list.json"], "list.json"),
    ("demo out under a file", ["demo", "--out", "{d}/a_file/report"], "a_file"),
]


@pytest.mark.parametrize("argv, name", [c[1:] for c in CLI_CASES], ids=[c[0] for c in CLI_CASES])
def test_refusals_are_one_line_naming_the_option_or_file(files, capsys, argv, name):
    """Exit code 2 and exactly one line on stderr naming the option or file, no traceback."""
    code = cli.main([a.replace("{d}", str(files)) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, (code, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert name in lines[0], lines[0]


def test_build_bank_smallest_accepted_values_pass_the_checks(tmp_path):
    """The command reads the Cardboard prescription by default, a JSON file of it, and at most 1 MiB (which
    is not JSON here)."""
    from controlgs_adapter.commands.optics import _prescription

    assert _prescription("cardboard").spec == Prescription(CARDBOARD).spec
    p = tmp_path / "rx.json"
    p.write_text(json.dumps(CARDBOARD))
    assert _prescription(str(p)).spec == Prescription(CARDBOARD).spec
    big = tmp_path / "big.json"
    big.write_bytes(b" " * (1 << 20))  # exactly 1 MiB is read (and is not JSON)
    with pytest.raises(FileFormatError, match="not a JSON file"):
        _prescription(str(big))
