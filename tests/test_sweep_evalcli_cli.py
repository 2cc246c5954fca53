"""The ``controlgs`` command line by hand: every documented option default compared with its number,
the refusals of each command's checks (one line, the option named), the optional-dependency table
per (command, action), the error branches of ``main`` and the small helpers of the commands."""

from __future__ import annotations

import argparse
import sys
import types
from pathlib import Path
from typing import Any

import pytest

from controlgs_adapter import cli
from controlgs_adapter.errors import InputValueError


def _parse(*argv: str) -> argparse.Namespace:
    return cli.build_parser().parse_args(list(argv))


def _err(capsys: pytest.CaptureFixture[str], command: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"controlgs {command}: error: "), err
    return err[0][len(f"controlgs {command}: error: "):]


# ------------------------------------------------------------------------------ defaults
def test_train_and_eval_defaults():
    a = _parse("train")
    assert (a.out, a.variant, a.resolution, a.test_views, a.optics, a.seed, a.seeds, a.progress) == \
        ("controlgs-run", "ar", None, None, "fast", 0, None, True)
    assert (a.iterations, a.psf_fraction, a.lr, a.cond_dim, a.checkpoint_every, a.effects) == (1000, 0.1, 3e-3, 8, 500, None)
    assert (a.batch_size, a.scenes, a.dist_backend, a.dist_timeout, a.exchange) == (1, None, None, 300.0, "auto")
    assert (a.ablations, a.ablation, a.cache_mib, a.device, a.holdout, a.rasterizer, a.renderer) == \
        (True, [], 1024, "cpu", None, None, None)
    assert (a.model, a.data, a.family, a.model_iteration, a.allow_unquantized, a.white_background, a.images) == \
        (None,) * 7
    assert _parse("train", "--no-ablations").ablations is False
    assert _parse("train", "--ablation", "wo_lens", "--ablation", "state_blind").ablation == ["wo_lens", "state_blind"]
    e = _parse("eval")
    assert (e.run, e.out, e.effects, e.lpips_weights, e.optics, e.seed, e.seeds, e.func.__module__) == \
        ("controlgs-run", None, None, None, "fast", 0, None, "controlgs_adapter.commands.eval")
    assert _parse("eval", "--lpips-weights", "a", "b").lpips_weights == ["a", "b"]
    assert _parse("eval", "--no-progress").progress is False


def test_demo_view_scene_optics_bench_defaults():
    d = _parse("demo")
    assert (d.out, d.ablations, d.iterations, d.resolution, d.variant) == ("report", True, 1000, None, "ar")
    v = _parse("view")
    assert (v.run, v.port, v.iterations, v.threads, v.resolution, v.test_views) == (None, 0, 150, None, None, None)
    b = _parse("scene", "build-backbone", "--out", "o")
    assert (b.variant, b.resolution, b.iterations, b.max_anchors, b.n_offsets, b.seed) == ("ar", 128, 1500, 3000, 5, 0)
    x = _parse("scene", "export", "--out", "o")
    assert (x.variant, x.resolution, x.scene_command) == ("ar", 128, "export")
    o = _parse("optics", "build-bank")
    assert (o.out, tuple(o.grid), o.psf_size, o.pupil_samples, o.min_pitch_px, o.prescription) == \
        (Path("psf_bank.safetensors"), (30, 30), 33, 192, 0.125, None)
    c = _parse("optics", "bench")
    assert (c.sizes, c.radiometry, c.tols, c.repeat, c.scaling, c.zone, c.exact_max, c.threads, c.out) == \
        (["256", "512", "1024", "576x1024"], ["radiance", "energy"], [0.02], 3, True, 5, 1024, 2, None)
    assert _parse("optics", "bench", "--doc").out == Path("docs") and _parse("optics", "bench", "--no-scaling").scaling is False
    w = _parse("optics", "fit-prewarp", "--out", "l.safetensors")
    assert (w.bank, w.size, w.modes, w.radiometry) == (None, 256, ["distortion", "exact"], "radiance")
    n = _parse("bench")
    assert (n.out, n.resolution, n.iterations, n.test_views, n.quick, n.variant, n.seed) == \
        (None, 96, None, None, False, "ar", 0)
    assert _parse("bench", "--doc").out == Path("docs") / "benchmarks.md"
    assert _parse("plugins").strict is False
    assert cli.COMMANDS == ("plugins", "optics", "scene", "train", "eval", "demo", "bench", "view")


def test_bench_settings_from_the_command_line():
    from controlgs_adapter.benchmarking.accuracy_time import BenchSettings
    from controlgs_adapter.commands.bench import settings_from_args

    s = settings_from_args(_parse("bench"))
    assert s == BenchSettings(resolution=96, variant="ar", seed=0)
    assert (s.iterations, s.test_views, s.repeats) == (100, 4, 20)
    q = settings_from_args(_parse("bench", "--quick", "--variant", "vr", "--seed", "3", "--resolution", "32"))
    assert (q.iterations, q.phase_iterations, q.repeats, q.test_views, q.downsample, q.power_saving) == \
        (20, 6, 5, 1, (1.0, 4.0), (0.0, 0.6))
    assert (q.resolution, q.variant, q.seed) == (32, "vr", 3)
    o = settings_from_args(_parse("bench", "--quick", "--iterations", "7", "--test-views", "3"))
    assert (o.iterations, o.test_views, o.repeats) == (7, 3, 5)  # given options win over --quick's
    assert settings_from_args(_parse("bench", "--iterations", "9")).iterations == 9


def test_train_config_of_each_adapter():
    from controlgs_adapter.commands.adapters import DEMO_ITERATIONS, train_config

    assert DEMO_ITERATIONS == 1000
    a = _parse("train", "--iterations", "12", "--lr", "0.5", "--cond-dim", "3", "--psf-fraction", "0.25",
               "--optics", "exact", "--checkpoint-every", "4", "--seed", "9", "--batch-size", "2")
    c = train_config(a, "controlgs")
    assert (c.iterations, c.lr, c.cond_dim, c.psf_fraction, c.psf_mode, c.checkpoint_every, c.seed, c.batch_size) == \
        (12, 0.5, 3, 0.25, "exact", 4, 9, 2)
    assert (c.modules, c.state_blind) == (None, False)
    assert (train_config(a, "wo_lens").modules, train_config(a, "wo_lens").state_blind) == (("resample", "display"), False)
    assert train_config(a, "wo_display").modules == ("lens", "resample")
    assert (train_config(a, "state_blind").modules, train_config(a, "state_blind").state_blind) == \
        (("lens", "resample", "display"), True)
    assert train_config(a, "controlgs", seed=5).seed == 5 and train_config(a, "controlgs", seed=0).seed == 0
    demo = _parse("demo")  # no --batch-size: TrainConfig's
    assert train_config(demo, "controlgs").batch_size == 1 and train_config(demo, "controlgs").iterations == 1000


def test_effects_from_lists():
    from controlgs_adapter.commands.adapters import effects_from
    from controlgs_adapter.training import DEFAULT_EFFECTS

    assert effects_from(None) == dict(DEFAULT_EFFECTS) and effects_from(None) is not DEFAULT_EFFECTS
    names = list(DEFAULT_EFFECTS)
    assert effects_from([names[1], names[0]]) == {names[0]: True, names[1]: True}
    assert effects_from(f" {names[0]} ,, ") == {names[0]: True}
    for bad in ("", " , ", "nope", f"{names[0]},nope", []):
        with pytest.raises(InputValueError, match="--effects must be a comma-separated list of"):
            effects_from(bad)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------ main()
def test_main_help_version_and_errors(capsys, tmp_path):
    assert cli.main([]) == 0 and "usage: controlgs" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0
    from controlgs_adapter._version import __version__

    assert capsys.readouterr().out.strip() == f"controlgs-adapter {__version__}"
    # an OSError (an unreadable file) is one line naming its type, exit 2
    if Path("/proc/self/mem").is_file():
        assert cli.main(["optics", "figures", "--prescription", "/proc/self/mem"]) == 2
        assert _err(capsys, "optics").startswith("OSError: ")


def test_main_missing_module_is_one_line(capsys, monkeypatch):
    # a module that cannot be imported: the package named, with the extra to install
    monkeypatch.setitem(sys.modules, "controlgs_adapter.downstream.optics.generate", None)
    assert cli.main(["optics", "figures"]) == 2
    msg = _err(capsys, "optics")
    assert msg == ("needs the Python package 'controlgs_adapter.downstream.optics.generate', which is not installed "
                   "(pip install 'controlgs-adapter[demo]' installs the optional ones)")
    # another ImportError (a name missing from a module): its own message on one line
    monkeypatch.setitem(sys.modules, "controlgs_adapter.downstream.optics.generate", types.ModuleType("standin"))
    assert cli.main(["optics", "figures"]) == 2
    msg = _err(capsys, "optics")
    assert msg == ("cannot import name 'lens_figures' from 'standin' (unknown location) (pip install "
                   "'controlgs-adapter[demo]' installs the optional ones)")


@pytest.mark.parametrize("argv, needs", [
    (["demo", "--out", "{d}/r"], "controlgs demo (the built-in scene and the report's plots) needs scikit-image"),
    (["optics", "bench"], "controlgs optics bench (the optics benchmark's test image and plot) needs scikit-image"),
    (["scene", "export", "--out", "{d}/x"], "controlgs scene export (exporting the built-in scene's views as PNG) "
                                            "needs scikit-image"),
])
def test_optional_dependencies_per_command_and_action(capsys, monkeypatch, tmp_path, argv, needs):
    """A stand-in module without a file counts as missing (extras.py): the command stops before its
    work with the extra to install."""
    monkeypatch.setitem(sys.modules, "skimage", types.ModuleType("skimage"))
    assert cli.main([a.replace("{d}", str(tmp_path)) for a in argv]) == 2
    assert _err(capsys, argv[0]) == f"{needs}, which is not installed: pip install 'controlgs-adapter[demo]'"
    assert not (tmp_path / "r").exists()


def test_commands_that_do_not_need_the_missing_extra(capsys, monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "skimage", types.ModuleType("skimage"))
    # eval needs matplotlib only: it goes on to its own check of the run folder
    assert cli.main(["eval", "--run", str(tmp_path)]) == 2
    assert _err(capsys, "eval") == (f"{tmp_path}: no controlgs.controlgs.safetensors (train one with "
                                    f"`controlgs train --out {tmp_path}`)")
    # optics figures needs neither
    assert cli.main(["optics", "figures", "--prescription", str(tmp_path / "none.json")]) == 2
    assert _err(capsys, "optics") == f"--prescription {tmp_path / 'none.json'}: no such file"
    monkeypatch.setitem(sys.modules, "matplotlib", types.ModuleType("matplotlib"))
    assert cli.main(["eval", "--run", str(tmp_path)]) == 2
    assert _err(capsys, "eval").startswith("controlgs eval (the report's plots) needs matplotlib")


# ------------------------------------------------------------------------------ optics checks
@pytest.mark.parametrize("args, message", [
    (["--psf-size", "4"], "--psf-size must be an odd integer >= 5, got 4"),
    (["--psf-size", "3"], "--psf-size must be an odd integer >= 5, got 3"),
    (["--grid", "0", "5"], "--grid GY GX must both be >= 1, got 0 5"),
    (["--grid", "5", "0"], "--grid GY GX must both be >= 1, got 5 0"),
    (["--pupil-samples", "3"], "--pupil-samples must be >= 4, got 3"),
    (["--min-pitch-px", "0"], "--min-pitch-px must be a finite number > 0, got 0.0"),
    (["--min-pitch-px", "inf"], "--min-pitch-px must be a finite number > 0, got inf"),
    (["--min-pitch-px", "nan"], "--min-pitch-px must be a finite number > 0, got nan"),
    (["--prescription", "{d}/none.json"], "--prescription {d}/none.json: no such file"),
    (["--prescription", "{d}/bad.json"], "--prescription {d}/bad.json: not a JSON file: "),
    (["--prescription", "{d}/wrong.json"], "--prescription {d}/wrong.json: "),
])
def test_build_bank_refusals(capsys, tmp_path, args, message):
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "wrong.json").write_text('{"surfaces": 3}')
    d = str(tmp_path)
    argv = ["optics", "build-bank", "--out", f"{d}/b.safetensors", *[a.replace("{d}", d) for a in args]]
    assert cli.main(argv) == 2
    assert _err(capsys, "optics").startswith(message.replace("{d}", d))
    assert not (tmp_path / "b.safetensors").exists()


def test_build_bank_smallest_accepted_values_pass_the_checks(tmp_path):
    from controlgs_adapter.commands.optics import _prescription
    from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription
    from controlgs_adapter.errors import FileFormatError

    assert _prescription(None).spec == Prescription(CARDBOARD).spec
    import json

    p = tmp_path / "rx.json"
    p.write_text(json.dumps(CARDBOARD))
    assert _prescription(p).spec == Prescription(CARDBOARD).spec
    big = tmp_path / "big.json"
    big.write_bytes(b" " * (1 << 20))  # exactly 1 MiB is read (and is not JSON)
    with pytest.raises(FileFormatError, match="not a JSON file"):
        _prescription(big)


# ------------------------------------------------------------------------------ helpers
def test_seed_folders(tmp_path):
    from controlgs_adapter.commands.eval import seed_folders

    assert seed_folders(tmp_path, 4, None) == [(4, tmp_path)]
    for name in ("seed-3", "seed-12", "seed--1", "seed-x"):
        (tmp_path / name).mkdir()
    (tmp_path / "seed-7").write_text("")  # a file, not a seed folder
    assert seed_folders(tmp_path, 0, None) == [(-1, tmp_path / "seed--1"), (3, tmp_path / "seed-3"),
                                               (12, tmp_path / "seed-12")]
    assert seed_folders(tmp_path, 3, 2) == [(3, tmp_path / "seed-3"), (4, tmp_path / "seed-4")]
    assert seed_folders(tmp_path, 3, 1) == [(3, tmp_path)]
    for bad in (0, -2, True, 1.5):
        with pytest.raises(InputValueError, match="--seeds must be an int >= 1"):
            seed_folders(tmp_path, 0, bad)  # type: ignore[arg-type]


def test_view_adapters_of_a_run_folder(tmp_path):
    from controlgs_adapter.commands.view import QUICK_ITERATIONS, VIEW_RESOLUTION, _adapters

    assert (QUICK_ITERATIONS, VIEW_RESOLUTION) == (150, 128)
    with pytest.raises(InputValueError, match=f"{tmp_path}: no controlgs.controlgs.safetensors"):
        _adapters(tmp_path)
    for n in ("controlgs", "state_blind", "other"):
        (tmp_path / f"{n}.controlgs.safetensors").write_text("")
    assert _adapters(tmp_path) == {"controlgs": tmp_path / "controlgs.controlgs.safetensors",
                                   "state_blind": tmp_path / "state_blind.controlgs.safetensors"}


def test_view_refusals(capsys, tmp_path):
    assert cli.main(["view", "--port", "65536"]) == 2
    assert "--port" in _err(capsys, "view")
    assert cli.main(["view", "--port", "-1"]) == 2
    assert "--port" in _err(capsys, "view")
    assert cli.main(["view", "--run", str(tmp_path / "none")]) == 2
    assert _err(capsys, "view") == f"--run {tmp_path / 'none'}: no such folder"
    assert cli.main(["view", "--run", str(tmp_path)]) == 2
    assert "no controlgs.controlgs.safetensors" in _err(capsys, "view")


def test_plugins_what_line():
    from controlgs_adapter.commands.plugins import _what
    from controlgs_adapter.plugins import PluginInfo

    class Short:
        """Does one thing with :class:`~a.B` and ``code``.

        More text that is not shown."""

    class Long:
        """A very long first paragraph that goes on and on beyond sixty characters for sure,
        over two lines."""

    assert _what(PluginInfo("backend", "s", "p", "src", Short)) == "Does one thing with a.B and code."
    assert _what(PluginInfo("backend", "s", "p", "src", Short())) == "Does one thing with a.B and code."
    long = _what(PluginInfo("rasterizer", "l", "p", "src", Long))
    assert long == "A very long first paragraph that goes on and on beyond si..."  # 57 characters + "..."
    assert _what(PluginInfo("backend", "l", "p", "src", Long), width=200).endswith("over two lines.")
    assert len(_what(PluginInfo("backend", "l", "p", "src", Long), width=60)) <= 60
    exact = type("Exact", (), {"__doc__": "x" * 60})
    assert _what(PluginInfo("backend", "e", "p", "src", exact)) == "x" * 60
    assert _what(PluginInfo("backend", "e", "p", "src", type("E", (), {"__doc__": "x" * 61}))) == "x" * 57 + "..."
    # a cut after a space: the space is dropped before the dots
    spaced = type("S", (), {"__doc__": "x" * 56 + " yyyyyy"})
    assert _what(PluginInfo("backend", "e", "p", "src", spaced)) == "x" * 56 + "..."


def test_plugins_listing(capsys):
    from controlgs_adapter.commands.plugins import run

    assert run(argparse.Namespace(strict=False)) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].split() == ["kind", "name", "plugin", "source", "what"]
    assert set(out[1].replace(" ", "")) == {"-"}
    assert any(line.startswith("stage") and "[order" in line for line in out)
    assert "built-in" in "\n".join(out)
    assert out[-1].startswith("backends and rasterizers are tried in the order listed") or any(
        line.startswith("FAILED: ") for line in out)
    # one blank line between kinds, none inside a kind
    body = out[2:]
    rows = body[:next(i for i, line in enumerate(body) if line.startswith("backends and rasterizers")) - 1]
    items = [line for line in rows if line]
    want: list[str] = []
    for i, line in enumerate(items):
        if i and line.split()[0] != items[i - 1].split()[0]:
            want.append("")
        want.append(line)
    assert rows == want and want.count("") == 3  # backend | stage | schedule | rasterizer


def test_load_renderer_refusals(tmp_path, monkeypatch):
    from controlgs_adapter.commands.common import RasterizerRenderer, load_renderer

    (tmp_path / "rr.py").write_text(
        "class K:\n    pass\n\nnumber = 3\n\ndef few(model):\n    return None\n\n"
        "class BadVisible:\n    def visible(self, model):\n        return None\n\n"
        "    def render(self, model, camera, visible, background):\n        return None\n\n"
        "bad_visible = BadVisible()\nbuiltin = max\n")
    f = tmp_path / "rr.py"
    for attr, message in (("K", "K is a class; name an instance of it or a function"),
                          ("number", r"number does not fit the render protocol \(a int\)"),
                          ("few", "few does not fit the render protocol"),
                          ("bad_visible", "bad_visible does not fit the render protocol")):
        with pytest.raises(InputValueError, match=message):
            load_renderer(f"{f}:{attr}")
    assert load_renderer(f"{f}:builtin") is not None  # no signature to inspect: accepted
    with pytest.raises(InputValueError, match=f"no such file {tmp_path / 'none.py'}"):
        load_renderer(f"{tmp_path / 'none.py'}:fn")
    with pytest.raises(InputValueError, match="must be MODULE:ATTR"):
        load_renderer("nocolon")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputValueError, match=r"no module named 'no_such_mod_xyz' .*path/to/file.py:fn\)"):
        load_renderer("no_such_mod_xyz:fn")
    with pytest.raises(InputValueError, match="no module named 'no_such_pkg_xyz'"):
        load_renderer("no_such_pkg_xyz.sub:fn")
    assert str(tmp_path) not in sys.path  # the current folder is taken off the path again
    r = RasterizerRenderer(load_renderer("rr:builtin"), "torch")
    assert repr(r).endswith(" with rasterizer 'torch'")


def test_apply_run_defaults_refuses_a_broken_run_file(tmp_path):
    from controlgs_adapter.commands.common import apply_run_defaults

    ns: Any = argparse.Namespace(model=None, data="mine", holdout=None, resolution=None)
    assert apply_run_defaults(ns, tmp_path) is None and ns.model is None
    (tmp_path / "run.json").write_text('{"model": "m", "data": "d", "holdout": 4, "resolution": null, "seed": 3}')
    assert apply_run_defaults(ns, tmp_path) == {"model": "m", "data": "d", "holdout": 4, "resolution": None, "seed": 3}
    assert (ns.model, ns.data, ns.holdout, ns.resolution) == ("m", "mine", 4, None)
    assert not hasattr(ns, "seed")
    (tmp_path / "run.json").write_text("{oops")
    with pytest.raises(InputValueError, match=f"{tmp_path / 'run.json'}: not a controlgs run file"):
        apply_run_defaults(ns, tmp_path)


def test_train_refusals_before_any_loading(capsys, tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("")
    # --scenes trains built-in scenes only (and takes no run-folder lock: each process locks its scenes)
    assert cli.main(["train", "--model", "m", "--data", "d", "--scenes", "ar", "--out", str(blocker / "run")]) == 2
    assert _err(capsys, "train") == "--scenes trains built-in scenes; it does not combine with --model/--data"
    # rank 0 takes the run folder's lock (which cannot be made under a file); another rank does not
    assert cli.main(["train", "--model", "m", "--out", str(blocker / "run")]) == 2
    assert str(blocker) in _err(capsys, "train")
    monkeypatch.setenv("RANK", "1")
    assert cli.main(["train", "--model", "m", "--out", str(blocker / "run")]) == 2
    assert _err(capsys, "train") == "give both --model MODEL_DIR and --data DATA_DIR (or neither, for the built-in scene)"


def test_scene_export_writes_every_view(tmp_path, capsys, monkeypatch):
    import matplotlib.image

    from controlgs_adapter.scene import load_builtin_scene

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # the export renders through the scene cache
    assert cli.main(["scene", "export", "--resolution", "16", "--out", str(tmp_path)]) == 0
    assert len(list((tmp_path / "cache" / "controlgs-adapter" / "scene").iterdir())) == 1
    scene = load_builtin_scene("ar", 16, cache=True)
    n_train, n_test = len(scene.train_images), len(scene.test_images)
    assert capsys.readouterr().out.strip().endswith(f"{n_train} train and {n_test} test views written to {tmp_path}")
    assert sorted(p.name for p in (tmp_path / "train").iterdir()) == [f"{i:03d}.png" for i in range(n_train)]
    assert sorted(p.name for p in (tmp_path / "test").iterdir()) == [f"{i:03d}.png" for i in range(n_test)]
    for split, images in (("train", scene.train_images), ("test", scene.test_images)):
        for i in (0, len(images) - 1):
            png = matplotlib.image.imread(tmp_path / split / f"{i:03d}.png")[..., :3]
            assert png.shape == (16, 16, 3)
            # 8-bit PNG: within one level (matplotlib rounds x * 255 down or to nearest)
            assert float(abs(png - images[i].permute(1, 2, 0).numpy()).max()) <= 1 / 255 + 1e-6


def test_every_command_action_and_option_has_a_help_text():
    """``controlgs --help`` and each sub-command's ``--help`` describe everything they offer."""
    undocumented: list[str] = []

    def walk(p: argparse.ArgumentParser, path: list[str]) -> int:
        n = 0
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for ca in a._choices_actions:
                    n += 1
                    if not ca.help:
                        undocumented.append(" ".join(path + [ca.dest]))
                for name, sp in a.choices.items():
                    n += walk(sp, path + [name])
            elif not isinstance(a, argparse._HelpAction):
                n += 1
                if not a.help:
                    undocumented.append(" ".join(path + [a.option_strings[0] if a.option_strings else a.dest]))
        return n

    assert walk(cli.build_parser(), []) > 150  # every command, action and option was visited
    assert undocumented == []


def test_optics_figures_prints_json(capsys):
    import json

    assert cli.main(["optics", "figures"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["half_width_mm"] == 12.0  # Cardboard: a 24 mm wide display half
    assert figures["px_per_mm_display_at_1024"] == pytest.approx(1024 / 24.0)
