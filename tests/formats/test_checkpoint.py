"""The training checkpoint (``formats.checkpoint``): what a trainer writes under which names, the round
trip, and every file of another run or malformed file refused naming the file and the field."""

from __future__ import annotations

import json
import math

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import save_file

from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.formats import safetensors as st
from controlgs_adapter.formats.checkpoint import CHECKPOINT_KIND, Checkpoint, read_checkpoint, write_checkpoint
from controlgs_adapter.formats.safetensors import load_tensors
from controlgs_adapter.training import TrainConfig, Trainer

EFFECTS = {"lens": True, "resample": True, "display": True, "oled": True, "optics": {"mode": "distortion"}}


def _trainer(tiny, path, effects=EFFECTS):
    scene, model = tiny
    config = TrainConfig(iterations=2, checkpoint_every=0, psf_fraction=0.0)
    return Trainer(model, scene.views("train"), config, effects=effects, checkpoint=path)


def test_file_holds_the_live_state_under_the_documented_names(tiny, tmp_path):
    pytest.importorskip("skimage")
    path = tmp_path / "run.ckpt.safetensors"
    t = _trainer(tiny, path)
    try:
        t.train(progress=False)
        tensors, header = load_tensors(path, kind=CHECKPOINT_KIND, max_version=1)
        adapter = t.cgs.injector.state_dict()
        adam = t.optimizer.state_dict()
        want = {f"adapter.{k}": v for k, v in adapter.items()}
        want.update({f"optimizer.{i}.{k}": v for i, state in adam["state"].items() for k, v in state.items()})
        want["rng"] = t.generator.get_state()
        assert sorted(tensors) == sorted(want)
        for k, v in want.items():
            assert tensors[k].dtype == v.dtype and torch.equal(tensors[k], v.cpu()), k
        assert len(adam["state"]) == len(list(t.cgs.trainable_parameters()))  # Adam state of every parameter
        assert header["iteration"] == 2 and header["history"] == t.history
        assert header["modules"] == list(t.cgs.modules) == ["lens", "resample", "display"]
        assert header["effects"] == sorted(EFFECTS)
        assert header["param_groups"] == json.loads(json.dumps(adam["param_groups"]))  # tuples come back as lists
        assert header["fingerprint"] == t.cgs.fingerprint and header["data"] == t.data_fingerprint
        assert header["config"] == t.config.as_header()

        shapes = [p.shape for g in t.optimizer.param_groups for p in g["params"]]
        back = read_checkpoint(path, t.checkpoint_state(), shapes)
        assert back.iteration == 2 and back.history == t.history
        assert all(torch.equal(back.adapter[k], v) for k, v in adapter.items())
        shapes[0] = torch.Size([*shapes[0], 1])  # an optimizer whose first parameter has another shape
        with pytest.raises(FileFormatError, match=r"run\.ckpt\.safetensors.*'optimizer\.0\.exp_avg'"):
            read_checkpoint(path, t.checkpoint_state(), shapes)
    finally:
        t.cgs.unwrap()


def _ckpt(**over):
    base = dict(adapter={"conditions": torch.full((3, 1, 2), 0.5), "projections.lens.d4.weight": torch.ones(4, 2)},
                optimizer_state={0: {"step": 3.0, "exp_avg": torch.full((3, 1, 2), 0.1), "exp_avg_sq": torch.zeros(3, 1, 2)},
                                 1: {"step": torch.tensor(3.0), "exp_avg": torch.ones(4, 2), "exp_avg_sq": torch.ones(4, 2)}},
                param_groups=[{"lr": 0.01, "params": [0, 1]}], rng=torch.arange(8, dtype=torch.uint8), iteration=3,
                history=[1.0, 0.5, 0.25], config={"lr": 0.01, "iterations": 10, "checkpoint_every": 5, "loss": {"l1": 1.0}},
                modules=["lens"], effects=["lens"], fingerprint="fp", data="views")
    return Checkpoint(**{**base, **over})


_SHAPES = [torch.Size([3, 1, 2]), torch.Size([4, 2])]


def _raw_ckpt(path, tensors, header):
    h = {"kind": CHECKPOINT_KIND, "format_version": 1, **header}
    save_file(tensors, str(path), metadata={st.HEADER_KEY: json.dumps(h)})


def test_checkpoint_round_trip_and_tensor_names(tmp_path):
    c = _ckpt()
    p = write_checkpoint(tmp_path / "c.safetensors", c)
    with safe_open(str(p), framework="pt") as f:
        names = sorted(f.keys())
        assert f.get_tensor("optimizer.0.step").shape == () and float(f.get_tensor("optimizer.0.step")) == 3.0
    assert names == sorted(["adapter.conditions", "adapter.projections.lens.d4.weight", "rng"]
                           + [f"optimizer.{i}.{k}" for i in (0, 1) for k in ("step", "exp_avg", "exp_avg_sq")])
    # a resumed run may change iterations and checkpoint_every only
    like = _ckpt(config={**c.config, "iterations": 99, "checkpoint_every": 1})
    back = read_checkpoint(p, like, _SHAPES)
    assert back.iteration == 3 and back.history == [1.0, 0.5, 0.25] and back.config == c.config
    assert torch.equal(back.adapter["conditions"], c.adapter["conditions"]) and torch.equal(back.rng, c.rng)
    assert torch.equal(back.optimizer_state[1]["exp_avg"], torch.ones(4, 2)) and back.param_groups == c.param_groups
    assert (back.modules, back.effects, back.fingerprint, back.data) == (["lens"], ["lens"], "fp", "views")


@pytest.mark.parametrize("like, words", [
    (dict(config={"lr": 0.02, "iterations": 10, "checkpoint_every": 5, "loss": {"l1": 1.0}}), "different config (lr)"),
    (dict(config={"lr": 0.01, "iterations": 10, "checkpoint_every": 5, "loss": {"l1": 2.0}}), "different config (loss)"),
    (dict(effects=["lens", "oled"]), "stages ['lens'], this trainer's are ['lens', 'oled']"),
    (dict(fingerprint="other"), "another backbone"),
    (dict(data="other"), "other views (data views)"),
    (dict(modules=["lens", "display"]), "trains modules ['lens'], this trainer ['lens', 'display']"),
    (dict(lens="0123456789abcdef"), "another lens (PSF bank None), this trainer's is 0123456789abcdef"),
    (dict(rng=torch.arange(9, dtype=torch.uint8)), "'rng' must be a torch.uint8 tensor of shape [9], got torch.uint8 [8]"),
    (dict(rng=torch.arange(8, dtype=torch.int64)), "'rng' must be a torch.int64 tensor of shape [8], got torch.uint8 [8]"),
    (dict(param_groups=[{"lr": 0.01, "params": [0]}, {"lr": 0.01, "params": [1]}]), "'param_groups' does not describe"),
    (dict(param_groups=[{"lr": 0.01, "params": [1, 0]}]), "'param_groups' does not describe"),
    (dict(adapter={"conditions": torch.zeros(3, 1, 3), "projections.lens.d4.weight": torch.ones(4, 2)}),
     "do not fit this adapter (missing, unexpected or mis-shaped: ['conditions'])"),
    (dict(adapter={"conditions": torch.zeros(3, 1, 2)}), "mis-shaped: ['projections.lens.d4.weight']"),
])
def test_checkpoint_of_another_run_is_refused(tmp_path, like, words):
    p = write_checkpoint(tmp_path / "c.safetensors", _ckpt())
    with pytest.raises(FileFormatError, match="c.safetensors: ") as e:
        read_checkpoint(p, _ckpt(**like), _SHAPES)
    assert words in str(e.value)


@pytest.mark.parametrize("edit, words", [
    (lambda t, h: t.update({"adapter.conditions": torch.full((3, 1, 2), math.nan)}), "['adapter.conditions'] hold NaN/Inf"),
    (lambda t, h: t.update({"optimizer.2.step": torch.tensor(1.0)}), "'optimizer.2.step' ([]) is not Adam state of this adapter's 2"),
    (lambda t, h: t.update({"optimizer.x.step": torch.tensor(1.0)}), "'optimizer.x.step'"),
    (lambda t, h: t.update({"optimizer.0.momentum": torch.zeros(3, 1, 2)}), "'optimizer.0.momentum'"),
    (lambda t, h: t.update({"optimizer.1.exp_avg": torch.zeros(2, 4)}), "'optimizer.1.exp_avg' ([2, 4])"),
    (lambda t, h: t.update({"extra": torch.zeros(1)}), "unexpected tensors ['extra']"),
    (lambda t, h: t.pop("rng"), "'rng' must be a torch.uint8 tensor of shape [8], got none"),
    (lambda t, h: h.update(iteration=-1), "'iteration' must be an integer >= 0, got -1"),
    (lambda t, h: h.update(iteration=True), "'iteration' must be an integer >= 0, got True"),
    (lambda t, h: h.update(iteration=2.0), "'iteration' must be an integer >= 0, got 2.0"),
    (lambda t, h: h.update(history=[1.0, math.inf]), "'history' must be a list of finite losses"),
    (lambda t, h: h.update(history=[True]), "'history' must be a list of finite losses"),
    (lambda t, h: h.update(history={"a": 1}), "'history' must be a list of finite losses"),
    (lambda t, h: h.update(param_groups={"params": [0, 1]}), "'param_groups' does not describe"),
    (lambda t, h: h.update(config=[1]), "'config' must be an object with a 'loss' object"),
    (lambda t, h: h.update(config={"lr": 0.01, "loss": 1}), "'config' must be an object with a 'loss' object"),
])
def test_checkpoint_malformed_files_are_refused(tmp_path, edit, words):
    c = _ckpt()
    tensors, header = c.tensors(), c.header()
    edit(tensors, header)
    _raw_ckpt(tmp_path / "c.safetensors", tensors, header)
    with pytest.raises(FileFormatError, match="c.safetensors: ") as e:
        read_checkpoint(tmp_path / "c.safetensors", c, _SHAPES)
    assert words in str(e.value)


def test_checkpoint_step_of_any_shape_and_missing_history_accepted(tmp_path):
    c = _ckpt()
    tensors, header = c.tensors(), c.header()
    tensors["optimizer.1.step"] = torch.tensor([3.0])
    del header["history"]
    _raw_ckpt(tmp_path / "c.safetensors", tensors, header)
    back = read_checkpoint(tmp_path / "c.safetensors", c, _SHAPES)
    assert back.history == [] and back.optimizer_state[1]["step"].tolist() == [3.0]


@pytest.mark.parametrize("drop", ["lr", "loss"])
def test_checkpoint_missing_a_config_field_is_another_run(tmp_path, drop):
    c = _ckpt()
    header = c.header()
    header["config"] = {k: v for k, v in c.config.items() if k != drop}
    _raw_ckpt(tmp_path / "c.safetensors", c.tensors(), header)
    with pytest.raises(FileFormatError, match=rf"c.safetensors: checkpoint was written with a different config \({drop}\)"):
        read_checkpoint(tmp_path / "c.safetensors", c, _SHAPES)


def test_checkpoint_at_iteration_zero_with_integer_losses(tmp_path):
    """The smallest well-formed header values: iteration 0 (>= 0 is documented) and integer losses."""
    c = Checkpoint(adapter={"conditions": torch.zeros(2, 1, 2)}, optimizer_state={},
                   param_groups=[{"lr": 0.1, "params": [0]}], rng=torch.zeros(4, dtype=torch.uint8), iteration=0,
                   history=[2, 1], config={"lr": 0.1, "iterations": 5, "loss": {}}, modules=["lens"], effects=[],
                   fingerprint="f", data="d")
    p = write_checkpoint(tmp_path / "c.safetensors", c)
    back = read_checkpoint(p, c, [torch.Size([2, 1, 2])])
    assert back.iteration == 0 and back.history == [2, 1] and back.optimizer_state == {}
    assert back.param_groups == [{"lr": 0.1, "params": [0]}] and back.effects == []


def test_a_checkpoint_without_a_lens_record_resumes_under_the_trainers_lens(tmp_path):
    """Files written before the lens was recorded carry no ``lens``: they resume (under whatever lens the trainer
    simulates), while one that names a bank must name the trainer's."""
    p = write_checkpoint(tmp_path / "c.safetensors", _ckpt(lens="aaaa"))
    t, h = load_tensors(p, kind=CHECKPOINT_KIND, max_version=1)
    h = {k: v for k, v in h.items() if k not in ("kind", "format_version", "library_version", "lens")}
    _raw_ckpt(tmp_path / "old.safetensors", t, h)
    assert read_checkpoint(tmp_path / "old.safetensors", _ckpt(lens="bbbb"), _SHAPES).lens == "bbbb"
    assert read_checkpoint(p, _ckpt(lens="aaaa"), _SHAPES).lens == "aaaa"
    with pytest.raises(FileFormatError, match="another lens"):
        read_checkpoint(p, _ckpt(lens="bbbb"), _SHAPES)
