"""``controlgs eval`` on the built-in scene and ``controlgs train --scenes`` end to end at 16 px with a
cheap downstream path: the options reach the evaluation (``--test-views``, ``--effects``,
``--resolution``, the run's record) and the report's info records them; the many-scenes mode
writes each scene's adapters into its folder."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

pytest.importorskip("matplotlib")
pytest.importorskip("skimage")

from controlgs_adapter import ControlGS
from controlgs_adapter.cli import main
from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_backbone

pytestmark = pytest.mark.skipif(not (builtin_backbone_dir("ar") / "point_cloud").is_dir(),
                                reason="built-in backbone not baked")


def test_eval_of_a_built_in_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "run"
    run.mkdir()
    cgs = ControlGS.wrap(load_builtin_backbone("ar"), cond_dim=2)  # an untrained (zero) adapter: the backbone
    cgs.save(run / "controlgs.controlgs.safetensors")
    cgs.unwrap()
    (run / "run.json").write_text(json.dumps({"variant": "ar", "effects": ["display"], "iterations": 7, "seed": 3,
                                              "seeds": 1, "adapters": ["controlgs"], "rasterizer": "auto",
                                              "renderer": None}))
    out = tmp_path / "report"
    assert main(["eval", "--run", str(run), "--out", str(out), "--resolution", "16", "--test-views", "2",
                 "--no-progress"]) == 0
    printed = capsys.readouterr().out.split()
    assert printed == [str(out / f) for f in ("results.json", "heatmap.png", "comparison.png",
                                              "condition_response.png", "report.md")]
    data = json.loads((out / "results.json").read_text())
    info = data["info"]
    assert (info["resolution"], info["test_views"], info["seeds"], info["adapters"], info["effects"]) == \
        (16, 2, 1, ["controlgs"], ["display"])  # the effects of run.json
    assert (info["optics"], info["device"], info["rasterizer"], info["renderer"]) == ("fast", "cpu", "auto", None)
    assert (info["iterations"], info["seed"], info["test_sizes"]) == (7, 3, ["16x16"])
    assert "lpips_weights" not in info and info["load_s"] >= 0 and info["eval_s"] > 0
    assert set(data["methods"]) == {"no_ss", "ss", "ideal", "controlgs"}
    ss = torch.tensor(data["methods"]["ss"]["psnr"]["per_view"])
    assert ss.shape == (4, 5, 2)  # the paper's grid, the first 2 test views
    # a zero adapter renders the backbone: the same numbers as the SS-backbone
    assert data["methods"]["controlgs"]["psnr"]["per_view"] == data["methods"]["ss"]["psnr"]["per_view"]
    md = (out / "report.md").read_text()
    assert "averaged over the 2 test views and the 20 run-time settings" in md
    assert "Run: test_views = 2, seed = 3, scene = builtin-ar, resolution = 16, optics = fast" in md


def test_train_many_scenes_mode(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "runs"
    assert main(["train", "--scenes", "ar", "--out", str(out), "--iterations", "1", "--resolution", "16",
                 "--no-ablations", "--effects", "display", "--checkpoint-every", "0", "--no-progress",
                 "--seeds", "2", "--seed", "5"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    want = [out / "ar" / f"seed-{s}" / "controlgs.controlgs.safetensors" for s in (5, 6)]
    assert lines[-2:] == [f"[rank 0] ar controlgs: {p}" for p in want]
    assert all(p.is_file() for p in want) and not (out / "run.json").exists()


def test_optics_bench_and_fit_prewarp_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["optics", "bench", "--sizes", "16", "--radiometry", "radiance", "--repeat", "1", "--no-scaling",
                 "--exact-max", "16", "--threads", "1", "--out", str(tmp_path / "ob")]) == 0
    assert sorted(p.name for p in (tmp_path / "ob").iterdir()) == ["optics_bench.md", "optics_bench.png"]
    assert "16x16 radiance exact" in capsys.readouterr().out
    lut = tmp_path / "lut.safetensors"
    assert main(["optics", "fit-prewarp", "--size", "8", "--modes", "distortion", "--radiometry", "energy",
                 "--out", str(lut)]) == 0  # not the default radiometry: the option must reach the fit
    out = capsys.readouterr().out
    meta = json.loads(out[:out.rindex("}") + 1])
    assert (meta["size"], meta["radiometry"], list(meta["residuals"])) == ([8, 8], "energy", ["distortion"])
    assert lut.is_file() and out.strip().splitlines()[-1].startswith(f"wrote {lut} (")
