"""Mutation audit of the command line (``controlgs_adapter/commands/*``, ``cli.py``) and the ``controlgs
bench`` report: what the earlier tests left unobserved. ``controlgs plugins --strict`` and the listing's
column alignment; ``optics build-bank`` at its smallest accepted values; ``controlgs view`` on the
built-in scene (its options reach the session, the exact ground truth of any camera) and its refusals;
the resume messages of :func:`train_adapters`; the timings that ``eval`` / ``demo`` report (each a part of
the command's wall time); ``demo`` / ``train`` with ``--seeds 2`` (each seed its own training)."""

from __future__ import annotations

import json
import time
from typing import Any

import pytest
import torch

from controlgs_adapter import cli
from controlgs_adapter.scene import builtin_backbone_dir

needs_backbone = pytest.mark.skipif(not (builtin_backbone_dir("ar") / "point_cloud").is_dir(),
                                    reason="built-in backbone not baked")


def _err(capsys: pytest.CaptureFixture[str], command: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"controlgs {command}: error: "), err
    return err[0][len(f"controlgs {command}: error: "):]


# ------------------------------------------------------------------------------ plugins
def test_plugins_strict_option_fails_on_a_broken_plugin(monkeypatch, capsys):
    """``controlgs plugins --strict``: "fail if an installed plug-in does not load" (its help); without
    it the failure is listed and the command succeeds."""
    from test_plugins_third_party import _FakeDistribution, _FakeEntryPoint, _fake_distributions

    from controlgs_adapter import plugins

    monkeypatch.delenv("CONTROLGS_DISABLE_PLUGIN_AUTOLOAD", raising=False)
    monkeypatch.delenv("CONTROLGS_STRICT_PLUGINS", raising=False)
    _fake_distributions(monkeypatch, _FakeDistribution("broken-xr", "0.1", [
        _FakeEntryPoint("broken", ModuleNotFoundError("No module named 'cupy'"))]))
    plugins.reset_plugin_manager()
    try:
        assert cli.main(["plugins", "--strict"]) == 1
        captured = capsys.readouterr()
        assert "'broken' from broken-xr 0.1 failed to load" in captured.err and captured.out == ""
        plugins.reset_plugin_manager()
        with pytest.warns(RuntimeWarning, match="'broken' from broken-xr 0.1 failed to load"):
            assert cli.main(["plugins"]) == 0
        assert "FAILED: plug-in 'broken' from broken-xr 0.1" in capsys.readouterr().out
    finally:
        plugins.reset_plugin_manager()


def test_plugins_listing_columns_line_up(capsys):
    """Every column of the listing starts where its header does: each column is as wide as its
    longest cell (header included) plus two spaces."""
    import argparse

    from controlgs_adapter.commands.plugins import run

    assert run(argparse.Namespace(strict=False)) == 0
    lines = capsys.readouterr().out.splitlines()
    head = lines[0]
    starts = [head.index(h) for h in ("name", "plugin", "source", "what")]
    rows = [line for line in lines[2:] if line and not line.startswith(("backends and rasterizers", "FAILED"))]
    assert rows
    for line in rows:
        for s in starts:  # a new cell starts after two spaces of padding
            assert line[s - 2:s] == "  " and line[s] != " ", (line, s)
    # the first column is exactly as wide as its longest cell
    kinds = [line.split()[0] for line in rows]
    assert starts[0] == max(len(k) for k in [*kinds, "kind"]) + 2


# ------------------------------------------------------------------------------ optics build-bank
def test_build_bank_smallest_accepted_values(tmp_path, capsys):
    """The documented lower bounds are inclusive: ``--grid 1 1``, ``--psf-size 5`` (odd >= 5),
    ``--pupil-samples 4`` (>= 4) and a pitch below one pixel build a bank of that shape."""
    from controlgs_adapter.downstream.optics.bank import PSFBank

    out = tmp_path / "b.safetensors"
    assert cli.main(["optics", "build-bank", "--grid", "1", "1", "--psf-size", "5", "--pupil-samples", "4",
                     "--min-pitch-px", "0.5", "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith(f"wrote {out} (")
    bank = PSFBank.load(out)
    assert tuple(bank.psf.shape) == (3, 1, 1, 5, 5)  # three primaries, 1 x 1 field, 5 x 5 samples


# ------------------------------------------------------------------------------ view
@needs_backbone
def test_view_of_the_built_in_scene_with_a_run(tmp_path, monkeypatch, capsys):
    """``controlgs view --run RUN`` on the built-in scene (RUN has no run.json): ``--resolution`` and
    ``--test-views`` reach the session, which carries the scene's name and the exact ground truth of any
    camera (an orbit view has one too, unlike a user's data); the server's loop is replaced by two renders."""
    from controlgs_adapter import ControlGS
    from controlgs_adapter.scene import load_builtin_backbone
    from controlgs_adapter.viewer import parse_state
    from controlgs_adapter.viewer.server import ViewerServer

    run = tmp_path / "run"
    run.mkdir()
    cgs = ControlGS.wrap(load_builtin_backbone("ar"), cond_dim=2)  # zero conditions: renders as the backbone
    cgs.save(run / "controlgs.controlgs.safetensors")
    cgs.unwrap()
    seen: list[Any] = []

    def two_renders(self: ViewerServer, poll_interval: float = 0.5) -> None:
        n = len(self.session.cameras)
        seen.append((self.session, self.session.render(parse_state({}, n)),
                     self.session.render(parse_state({"azimuth": 15.0}, n))))

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(ViewerServer, "serve_forever", two_renders)
    assert cli.main(["view", "--run", str(run), "--resolution", "16", "--test-views", "1"]) == 0
    out = capsys.readouterr().out
    assert "controlgs view: builtin-ar, methods no_ss, ss, controlgs on cpu" in out
    (session, dataset, orbit), = seen
    assert len(session.cameras) == 1 and session.info()["name"] == "builtin-ar"
    assert dataset["size"] == [16, 16] and orbit["size"] == [16, 16]
    assert dataset["has_truth"] and orbit["has_truth"]  # the built-in scene: ray-cast truth of any camera
    psnr = {m["name"] if "name" in m else i: m["metrics"]["psnr"] for i, m in enumerate(orbit["methods"])}
    assert all(v is not None and v > 5 for v in psnr.values()), orbit["methods"]


def test_view_exact_truth_is_the_dataset_image():
    """``_exact_truth``: "the built-in scene's exact ground truth of any camera (ray cast, as its
    dataset's images)": a test camera's truth is its test image (float32, [3, H, W])."""
    from controlgs_adapter.commands.view import _exact_truth
    from controlgs_adapter.scene import load_builtin_scene

    for variant in ("ar", "vr"):
        builtin = load_builtin_scene(variant, 16, views=4, test_every=4)
        truth = _exact_truth(builtin)
        got = truth(builtin.test_cameras[0])
        assert got.dtype == torch.float32 and torch.equal(got, builtin.test_images[0]), variant


def test_view_refuses_zero_quick_iterations(tmp_path, monkeypatch, capsys):
    """Without ``--run`` the built-in scene's quick adapter needs ``--iterations`` >= 1: refused on one
    line before any training (the server is never started)."""
    from controlgs_adapter.viewer.server import ViewerServer

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(ViewerServer, "serve_forever", lambda self, poll_interval=0.5: None)
    assert cli.main(["view", "--resolution", "16", "--iterations", "0"]) == 2
    assert _err(capsys, "view").startswith("--iterations must be an integer in [1, ")


# ------------------------------------------------------------------------------ train_adapters
def test_train_adapters_resume_messages(tiny, tmp_path, capsys):
    """``train_adapters`` resumes from the run's checkpoint: a fresh run says nothing about resuming, a
    second run of the same length says where it resumes (and nothing else), a shorter one also says that
    it keeps what was trained; ``trained`` receives the iterations actually trained."""
    from controlgs_adapter.commands.adapters import train_adapters

    scene, model = tiny
    views = scene.views("train")

    def args(iterations: int) -> Any:
        return cli.build_parser().parse_args(["train", "--iterations", str(iterations), "--checkpoint-every", "1",
                                              "--effects", "display", "--no-progress", "--cond-dim", "2"])

    trained: dict[str, int] = {}
    paths = train_adapters(views, model, tmp_path, args(2), ["controlgs"], trained=trained)
    assert paths == {"controlgs": tmp_path / "controlgs.controlgs.safetensors"} and paths["controlgs"].is_file()
    assert trained == {"controlgs": 2} and capsys.readouterr().out == ""
    train_adapters(views, model, tmp_path, args(2), ["controlgs"], trained=trained)
    assert capsys.readouterr().out.splitlines() == ["controlgs: resuming at iteration 2"]
    train_adapters(views, model, tmp_path, args(1), ["controlgs"], trained=trained)
    assert capsys.readouterr().out.splitlines() == [
        "controlgs: resuming at iteration 2",
        "controlgs: the checkpoint is already at iteration 2 > --iterations 1; keeping what was trained"]
    assert trained == {"controlgs": 2}


# ------------------------------------------------------------------------------ eval / demo timings
def _timings_within(info: dict[str, Any], keys: tuple[str, ...], wall: float) -> None:
    """The reported durations (seconds, one decimal) are each >= 0 and together at most the command's
    wall time (measured around it here), allowing for the rounding of each."""
    got = [info[k] for k in keys]
    assert all(isinstance(v, float) and v >= 0 for v in got), info
    assert sum(got) <= wall + 0.05 * len(keys), (got, wall)


@needs_backbone
def test_eval_reported_times_are_parts_of_its_run(tmp_path, monkeypatch, capsys):
    """``controlgs eval`` reports ``load_s`` / ``eval_s`` in results.json's info: the time of loading
    and of the grid evaluation, both within the command's own time."""
    pytest.importorskip("matplotlib")
    from controlgs_adapter import ControlGS
    from controlgs_adapter.scene import load_builtin_backbone

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    run = tmp_path / "run"
    run.mkdir()
    cgs = ControlGS.wrap(load_builtin_backbone("ar"), cond_dim=2)
    cgs.save(run / "controlgs.controlgs.safetensors")
    cgs.unwrap()
    t0 = time.perf_counter()
    assert cli.main(["eval", "--run", str(run), "--resolution", "16", "--test-views", "1", "--effects", "display",
                     "--no-progress"]) == 0
    wall = time.perf_counter() - t0
    info = json.loads((run / "results.json").read_text())["info"]
    _timings_within(info, ("load_s", "eval_s"), wall)
    assert info["eval_s"] > 0 and (info["test_views"], info["effects"]) == (1, ["display"])


@needs_backbone
def test_demo_with_two_seeds(tmp_path, monkeypatch, capsys):
    """``controlgs demo --seeds 2 --seed 5``: one adapter per seed in ``seed-5/`` and ``seed-6/``, each trained
    with its own seed (they differ); the options reach the evaluation (``--resolution``, ``--test-views``)
    and info records them; the reported phase times are parts of the command's wall time."""
    pytest.importorskip("matplotlib")
    pytest.importorskip("skimage")
    from safetensors.torch import load_file

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "report"
    t0 = time.perf_counter()
    assert cli.main(["demo", "--out", str(out), "--resolution", "16", "--iterations", "1", "--test-views", "1",
                     "--effects", "display", "--checkpoint-every", "0", "--no-ablations", "--no-progress",
                     "--seeds", "2", "--seed", "5"]) == 0
    wall = time.perf_counter() - t0
    a, b = (load_file(out / f"seed-{s}" / "controlgs.controlgs.safetensors") for s in (5, 6))
    assert a.keys() == b.keys() and any(not torch.equal(a[k], b[k]) for k in a)
    data = json.loads((out / "results.json").read_text())
    info = data["info"]
    assert (info["resolution"], info["test_views"], info["seeds"], info["seed"], info["iterations"]) == (16, 1, 2, 5, 1)
    assert info["test_sizes"] == ["16x16"]
    _timings_within(info, ("load_s", "train_s", "eval_s", "figures_s"), wall)
    assert info["train_s"] > 0 and info["eval_s"] > 0


@needs_backbone
def test_train_built_in_with_two_seeds_and_one_ablation(tmp_path, monkeypatch, capsys):
    """``controlgs train --seeds 2 --seed 5 --ablation wo_lens`` on the built-in scene: ControlGS and only the
    chosen ablation, per seed in ``seed-<s>/``, each seed its own training; run.json records the run."""
    from safetensors.torch import load_file

    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "run"
    assert cli.main(["train", "--out", str(out), "--iterations", "1", "--resolution", "16", "--effects", "display",
                     "--checkpoint-every", "0", "--no-progress", "--seeds", "2", "--seed", "5",
                     "--ablation", "wo_lens"]) == 0
    want = [out / f"seed-{s}" / f"{n}.controlgs.safetensors" for s in (5, 6) for n in ("controlgs", "wo_lens")]
    assert capsys.readouterr().out.splitlines()[-4:] == [f"{p.name.split('.')[0]}: {p}" for p in want]
    record = json.loads((out / "run.json").read_text())
    assert {k: record[k] for k in ("variant", "effects", "iterations", "seed", "seeds", "adapters")} == \
        {"variant": "ar", "effects": ["display"], "iterations": 1, "seed": 5, "seeds": 2, "adapters": ["controlgs", "wo_lens"]}
    a, b = (load_file(out / f"seed-{s}" / "controlgs.controlgs.safetensors") for s in (5, 6))
    assert any(not torch.equal(a[k], b[k]) for k in a)
