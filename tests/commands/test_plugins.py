"""Tests of ``controlgs_adapter.commands.plugins``: ``controlgs plugins`` lists what is registered (aligned columns,
one block per kind, a short description of each), an installed plug-in that works, and a broken one (listed as
failed and skipped, or fatal with ``--strict``)."""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path

import pytest
import torch
from helpers.fake_plugins import _fake_distributions, _FakeDistribution, _FakeEntryPoint, _GoodPlugin

from controlgs_adapter import ControlGS, RuntimeState, cli, plugins
from controlgs_adapter.commands.plugins import _what, run
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.errors import PluginLoadError
from controlgs_adapter.plugins import PluginInfo

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "third_party_plugin.py"


@pytest.fixture()
def example():
    spec = importlib.util.spec_from_file_location("third_party_plugin_example", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_plugins_listing(capsys):
    """A header, a rule, one block per kind separated by one blank line, every column starting where its header
    does (each as wide as its longest cell plus two spaces), and the note on the order backends are tried in."""
    assert cli.build_parser().parse_args(["plugins"]).strict is False
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
    lines = out
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


def test_plugins_what_line():
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


def test_example_plugin_registers_lists_and_works(fresh_plugins, example, capsys):
    plugins.register_plugin(example, name="tiny_ng_example")
    assert cli.main(["plugins"]) == 0
    listing = capsys.readouterr().out
    rows = [line.split()[:4] for line in listing.splitlines()]
    assert ["backend", "tiny_ng", "tiny_ng_example", "runtime"] in rows
    assert ["stage", "vignette", "tiny_ng_example", "runtime"] in rows
    assert rows.index(["backend", "tiny_ng", "tiny_ng_example", "runtime"]) < rows.index(
        ["backend", "scaffold_gs", "controlgs_adapter.backends.builtin", "built-in"])  # plug-ins are tried first
    assert "Darkens the image towards the corners" in listing  # the stage's own description

    # the custom backend wraps its family (first match: plug-ins come before the built-ins)
    model = example.TinyNeuralGaussians(num_anchors=20)
    x = model.features
    with torch.no_grad():
        bare = model.head(x)
    cgs = ControlGS.wrap(model, modules=("resample",))
    assert cgs.backend.name == "tiny_ng" and [t.fc1 for t in cgs.targets] == ["head.0"]
    with torch.no_grad():
        cgs.injector.condition("resample").normal_()
        with cgs.conditioned(RuntimeState(downsample=8.0)):
            conditioned = model.head(x)
    assert not torch.equal(conditioned, bare)
    cgs.unwrap()

    # the custom stage runs in the pipeline, inserted by its order
    stage_cls = plugins.stages()["vignette"].obj
    assert stage_cls is example.VignetteStage
    pipeline = Pipeline.from_config({"lens": True, "vignette": {"strength": 0.5}, "resample": True, "oled": False})
    assert pipeline.names.index("vignette") == pipeline.names.index("lens") + 1
    image = torch.full((3, 8, 8), 0.5)
    direct = example.VignetteStage(0.5)(image, RuntimeState(), None)
    assert float(direct[0, 0, 0]) < float(direct[0, 4, 4]) <= 0.5
    eye = Pipeline.from_config({"vignette": {"strength": 0.5}, "oled": False})(image, RuntimeState())
    assert float(eye[0, 0, 0]) < float(eye[0, 4, 4])


def test_a_broken_plugin_is_reported_and_skipped_or_fatal_in_strict_mode(fresh_plugins, monkeypatch, capsys):
    _fake_distributions(monkeypatch, _FakeDistribution("broken-xr", "0.1", [
        _FakeEntryPoint("broken", ModuleNotFoundError("No module named 'cupy'")),
    ]), _FakeDistribution("acme-xr", "1.2.3", [_FakeEntryPoint("acme", _GoodPlugin())]))
    with pytest.warns(RuntimeWarning, match="'broken' from broken-xr 0.1 failed to load"):
        plugins.get_plugin_manager()
    assert "sharpen_test" in plugins.stages() and "scaffold_gs" in plugins.backends()  # the host still works
    capsys.readouterr()
    assert cli.main(["plugins"]) == 0  # listed as failed; the warning was given when the manager was built
    assert "FAILED: plug-in 'broken' from broken-xr 0.1 failed to load: ModuleNotFoundError" in capsys.readouterr().out
    plugins.reset_plugin_manager()
    with pytest.warns(RuntimeWarning, match=r"'broken' from broken-xr 0\.1 failed to load.*CONTROLGS_STRICT_PLUGINS=1"):
        assert cli.main(["plugins"]) == 0  # the command warns too (one printed line outside a test's recording)
    assert "FAILED: plug-in 'broken' from broken-xr 0.1" in capsys.readouterr().out
    plugins.reset_plugin_manager()
    assert cli.main(["plugins", "--strict"]) == 1  # "fail if an installed plug-in does not load"
    captured = capsys.readouterr()
    assert "'broken' from broken-xr 0.1 failed to load" in captured.err and captured.out == ""

    plugins.reset_plugin_manager()
    with pytest.raises(PluginLoadError, match="'broken' from broken-xr 0.1.*cupy"):
        plugins.get_plugin_manager(strict=True)
    plugins.reset_plugin_manager()
    monkeypatch.setenv("CONTROLGS_STRICT_PLUGINS", "1")
    capsys.readouterr()
    assert cli.main(["plugins"]) == 1
    assert "'broken' from broken-xr 0.1 failed to load" in capsys.readouterr().err
