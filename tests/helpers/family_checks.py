"""Checks shared by the backbone-family tests: wrap a model, verify identity at init, that one anchor's
condition reaches exactly its rows, and the adapter round trip; cameras, reference Scaffold-GS models and
Gaussian comparisons for them (``helpers.family_contract`` builds the family contract on these)."""

from __future__ import annotations

from argparse import Namespace
from pathlib import Path

import torch

from controlgs_adapter import RuntimeState
from controlgs_adapter.backend import get_attr_path
from controlgs_adapter.controlgs import ControlGS
from controlgs_adapter.rendering.protocol import ModelRenderer, renderer_for

STATE = RuntimeState(downsample=1, power_saving=0.4)  # display strength 0.5 for every anchor


def write_cfg_args(path: Path, **kw) -> None:
    """cfg_args as the families' train.py writes it: ``str(Namespace(**vars(args)))``."""
    path.write_text(str(Namespace(**kw)))


def outputs(model, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    with torch.no_grad():
        return {p: get_attr_path(model, p)(x) for p, x in inputs.items()}


def check_wrap_identity_and_rows(model, inputs: dict[str, torch.Tensor], ids: torch.Tensor, backend: str,
                                 rows_per_anchor: int, tmp_path: Path, reload) -> None:
    """``inputs``: decoder path -> input rows for anchors ``ids`` (``rows_per_anchor`` rows each).
    ``reload()`` returns a fresh copy of the same backbone (to load the saved adapter onto)."""
    before = outputs(model, inputs)
    assert type(renderer_for(model)) is ModelRenderer  # the family renders through the protocol by itself
    cgs = ControlGS.wrap(model, modules=("display",), cond_dim=4)
    assert cgs.backend.name == backend
    assert {t.decoder for t in cgs.targets} == set(inputs)
    # identity at init: zero conditions -> bit-identical outputs, inside and outside the block
    with cgs.conditioned(STATE, anchor_ids=ids):
        inside = outputs(model, inputs)
    for p in inputs:
        assert torch.equal(inside[p], before[p]), p
    # one anchor's condition reaches exactly its rows
    pos = len(ids) // 2
    anchor = int(ids[pos])
    with torch.no_grad():
        cgs.injector.condition("display")[anchor] = torch.linspace(-2.0, 2.0, 4)
    with cgs.conditioned(STATE, anchor_ids=ids):
        after = outputs(model, inputs)
    for p in inputs:
        changed = (after[p] != before[p]).any(dim=1).nonzero().squeeze(1)
        want = torch.arange(pos * rows_per_anchor, (pos + 1) * rows_per_anchor)
        assert torch.equal(changed, want), (p, changed, want)
    # outside the block: the backbone again
    for p, y in outputs(model, inputs).items():
        assert torch.equal(y, before[p])
    # save / load onto a fresh copy of the backbone
    path = cgs.save(tmp_path / "adapter.safetensors")
    other = reload()
    cgs2 = ControlGS.load(path, other)
    assert torch.equal(cgs2.injector.conditions, cgs.injector.conditions)
    with cgs2.conditioned(STATE, anchor_ids=ids):
        again = outputs(other, inputs)
    for p in inputs:
        assert torch.equal(again[p], after[p]), p
    cgs.unwrap()
    for p, y in outputs(model, inputs).items():
        assert torch.equal(y, before[p])


def make_camera(width: int = 64, height: int = 48, distance: float = 5.0):
    """A camera at (0, 0, -distance) looking along +z at the origin (OpenCV axes), focal length 40 px."""
    from controlgs_adapter import Camera

    w2c = torch.eye(4)
    w2c[2, 3] = distance
    k = torch.tensor([[40.0, 0.0, width / 2], [0.0, 40.0, height / 2], [0.0, 0.0, 1.0]])
    return Camera(w2c, k, width, height)


def reference_scaffold(anchor, offset, feat, log_scaling, decoders, *, dist: bool):
    """The reference Scaffold-GS model (backends/models/reference_model.py) holding the given tensors."""
    import copy

    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel

    a, k, _ = offset.shape
    ref = NeuralGaussianModel(a, feat_dim=feat.shape[1], n_offsets=k, add_opacity_dist=dist, add_cov_dist=dist,
                              add_color_dist=dist)
    with torch.no_grad():
        ref._anchor.copy_(anchor)
        ref._offset.copy_(offset)
        ref._anchor_feat.copy_(feat)
        ref._scaling.copy_(log_scaling)
    for name, dec in decoders.items():
        setattr(ref, name, copy.deepcopy(dec))
    return ref


def assert_same_gaussians(got, want, *, atol: float = 1e-6) -> None:
    for f in ("anchor_of", "offset_of", "visible_ids"):
        assert torch.equal(getattr(got, f), getattr(want, f)), f
    for f in ("means", "scales", "rotations", "opacities", "colors"):
        assert torch.allclose(getattr(got, f), getattr(want, f), atol=atol, rtol=1e-5), f
