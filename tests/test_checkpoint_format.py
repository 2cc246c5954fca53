"""The training-checkpoint file (controlgs_adapter.formats.checkpoint): what the file holds, read
back raw, equals the trainer's live state; a file of another run is refused before anything changes."""

import json

import pytest
import torch

pytest.importorskip("skimage")

from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.formats.checkpoint import CHECKPOINT_KIND, read_checkpoint
from controlgs_adapter.formats.safetensors import load_tensors
from controlgs_adapter.training import TrainConfig, Trainer

EFFECTS = {"lens": True, "resample": True, "display": True, "oled": True, "optics": {"mode": "distortion"}}



def _trainer(tiny, path, effects=EFFECTS):
    scene, model = tiny
    config = TrainConfig(iterations=2, checkpoint_every=0, psf_fraction=0.0)
    return Trainer(model, scene.views("train"), config, effects=effects, checkpoint=path)


def test_file_holds_the_live_state_under_the_documented_names(tiny, tmp_path):
    path = tmp_path / "run.ckpt.safetensors"
    t = _trainer(tiny, path)
    try:
        t.train(progress=False)
        tensors, header = load_tensors(path, kind=CHECKPOINT_KIND, max_version=1)
        adapter = t.cgs.injector.state_dict()
        adam = t.optimizer.state_dict()
        want = {f"adapter.{k}": v for k, v in adapter.items()}
        want.update({f"optimizer.{i}.{k}": v for i, st in adam["state"].items() for k, v in st.items()})
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


def test_checkpoint_through_other_stages_is_refused(tiny, tmp_path):
    path = tmp_path / "run.ckpt.safetensors"
    t = _trainer(tiny, path)
    try:
        t.train(until=1, progress=False)
    finally:
        t.cgs.unwrap()
    # same condition modules, but the OLED stage is off: the run differs
    other = _trainer(tiny, path, effects={k: v for k, v in EFFECTS.items() if k != "oled"})
    try:
        with pytest.raises(FileFormatError, match=r"run\.ckpt\.safetensors.*stages .*'oled'"):
            other.resume()
        assert other.iteration == 0 and other.history == []
    finally:
        other.cgs.unwrap()
