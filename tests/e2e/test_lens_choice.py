"""Choosing the headset lens from the command line only: a distortion profile (the Oculus DK1 example) gets its
pre-warp fitted (`controlgs optics fit-prewarp --lens`), an adapter is trained through it (`controlgs train
--lens`), the run records it, and `controlgs eval` and `controlgs view` take it back; the eye images are those
of that lens (the ideal render scored through it differs from the Cardboard's), and a lens that cannot load
writes nothing."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import pytest

pytest.importorskip("matplotlib")  # the report's plots

from helpers.cli_runs import MODEL, error_line, needs_backbone, snapshot, write_tiny_colmap

from controlgs_adapter.cli import main
from controlgs_adapter.downstream.optics.lenses import load_lens
from controlgs_adapter.viewer.server import ViewerServer

#: a profile shipped with the examples
PROFILE = Path(__file__).resolve().parents[2] / "examples" / "lenses" / "oculus_dk1_left.opencv.json"
#: a 3-iteration adapter through the lens and its optics at 24 px
ADAPTER = ["--iterations", "3", "--no-ablations", "--effects", "lens,optics", "--checkpoint-every", "0", "--no-progress",
           "--resolution", "24"]


@needs_backbone
def test_train_eval_and_view_through_a_distortion_profile(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    data = write_tiny_colmap(tmp_path / "scene")
    profile = Path(shutil.copy(PROFILE, tmp_path / "dk1.json"))
    run, report, cardboard = tmp_path / "run", tmp_path / "report", tmp_path / "cardboard"

    # the pre-warp fitted for the profile's bank, beside it: `--lens dk1.json` then finds it (no chief-ray fallback)
    lut = tmp_path / "dk1_prewarp_lut.safetensors"
    assert main(["optics", "fit-prewarp", "--lens", str(profile), "--size", "8", "--modes", "distortion", "exact",
                 "--out", str(lut)]) == 0
    assert load_lens(profile).prewarp == lut

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--lens", str(profile),
                     *ADAPTER]) == 0
    assert not [w for w in caught if "pre-warp" in str(w.message)]  # a lens without its LUT warns (chief rays)
    record = json.loads((run / "run.json").read_text())
    assert record["lens"] == str(profile.resolve()) and record["effects"] == ["lens", "optics"]

    assert main(["eval", "--run", str(run), "--out", str(report), "--test-views", "1", "--no-progress"]) == 0
    info = json.loads((report / "results.json").read_text())["info"]
    assert info["lens"] == str(profile.resolve())
    assert main(["eval", "--run", str(run), "--out", str(cardboard), "--test-views", "1", "--no-progress",
                 "--lens", "cardboard"]) == 0
    ideal = [json.loads((f / "results.json").read_text())["methods"]["ideal"]["psnr"]["mean"] for f in (report, cardboard)]
    assert ideal[0] != pytest.approx(ideal[1], abs=1e-3), ideal  # the ground truth seen through two different lenses

    served: list[ViewerServer] = []  # the viewer serves the run's lens (its server returns at once here)
    monkeypatch.setattr(ViewerServer, "serve_forever", lambda self, poll_interval=0.5: served.append(self))
    assert main(["view", "--run", str(run), "--port", "0", "--test-views", "1"]) == 0
    (server,) = served
    assert server.session.lens.spec == str(profile.resolve()) and server.session.lens.prewarp == lut
    capsys.readouterr()

    # a lens that cannot load: one line, exit 2, the report folder as it was
    before = snapshot(report)
    assert main(["eval", "--run", str(run), "--out", str(report), "--lens", str(tmp_path / "none.json")]) == 2
    assert error_line(capsys, "eval") == f"--lens {tmp_path / 'none.json'}: no such file"
    profile.unlink()  # the recorded lens is gone: named with run.json and its field
    assert main(["eval", "--run", str(run), "--out", str(report)]) == 2
    line = error_line(capsys, "eval")
    assert line.startswith(f"{run / 'run.json'}: field 'lens': lens {profile.resolve()}: no such file"), line
    assert snapshot(report) == before


@needs_backbone
def test_train_and_eval_through_the_shipped_compact_lens(tmp_path: Path) -> None:
    """`--lens compact`: the run records the name, eval takes it back, and the ground truth is seen through the
    compact lens (its ideal render differs from Cardboard's); the shipped LUT serves it without a warning."""
    data = write_tiny_colmap(tmp_path / "scene")
    run, report, cardboard = tmp_path / "run", tmp_path / "report", tmp_path / "cardboard"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--lens", "compact",
                     *ADAPTER]) == 0
    assert not [w for w in caught if "pre-warp" in str(w.message)]
    assert json.loads((run / "run.json").read_text())["lens"] == "compact"
    assert main(["eval", "--run", str(run), "--out", str(report), "--test-views", "1", "--no-progress"]) == 0
    assert json.loads((report / "results.json").read_text())["info"]["lens"] == "compact"
    assert main(["eval", "--run", str(run), "--out", str(cardboard), "--test-views", "1", "--no-progress",
                 "--lens", "cardboard"]) == 0
    ideal = [json.loads((f / "results.json").read_text())["methods"]["ideal"]["psnr"]["mean"] for f in (report, cardboard)]
    assert ideal[0] != pytest.approx(ideal[1], abs=1e-3), ideal
