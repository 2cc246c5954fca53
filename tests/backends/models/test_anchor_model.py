"""What every anchor family shares (``backends.models.anchor_model``): the prefilter (first three linear
scales, identity rotation when none is stored), Gaussians kept where the neural opacity is positive,
frozen evaluation models that refuse mis-shaped tensors, ``as_param``, the abstract base, and degenerate
anchors whose scales overflow yet keep every adapter gradient finite."""

from __future__ import annotations

import math

import helpers.compgs_files as compgs_files
import helpers.hac_files as hac_files
import helpers.octree_files as octree_files
import numpy as np
import pytest
import torch
from helpers.family_checks import make_camera
from helpers.family_models import family_kwargs, hac_kwargs, models_at
from torch import nn

from controlgs_adapter import Camera
from controlgs_adapter.backends.compgs import CompGSModel
from controlgs_adapter.backends.hac import HACModel, MaskedAnchorModel
from controlgs_adapter.backends.models.anchor_model import AnchorModel, anchor_visibility, as_param, assemble_gaussians
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.errors import InputValueError, ShapeError

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


#: anchors 0-1 on camera A's optical axis (depth 5), 2-4 on camera B's; each has one scale 0.5 and two 0.01
POS = torch.tensor([[0.0, 0, 5], [0, 0, 5], [0, 5, 0], [0, 5, 0], [0, 5, 0]])
LIN = torch.tensor([[0.5, 0.01, 0.01], [0.01, 0.01, 0.5], [0.5, 0.01, 0.01], [0.01, 0.01, 0.5], [0.01, 0.5, 0.01]])


def _models() -> dict[str, nn.Module]:
    return models_at(POS, torch.cat([LIN, torch.full((len(POS), 3), 0.02)], dim=1))


def _cameras() -> tuple[Camera, Camera]:
    """Two cameras at the origin, f = 40, 64 x 48, principal point (-6, 24): a point on the optical axis
    projects 6 px left of the image. A looks along world +z; B along world +y (camera axes: x = world x,
    y = -world z, z = world y)."""
    k = torch.tensor([[40.0, 0.0, -6.0], [0.0, 40.0, 24.0], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4)
    w2c[1:3, 1:3] = torch.tensor([[0.0, -1.0], [1.0, 0.0]])
    return Camera(torch.eye(4), k, 64, 48), Camera(w2c, k, 64, 48)


# ------------------------------------------------------------------------------------ the prefilter
def test_without_stored_rotations_the_prefilter_takes_the_identity_rotation():
    """With the identity rotation (what a family's file without rot_* means: CompGS's decoder resets
    rotations to identity) the long axis of anchors 0, 2 (world x) and 3 (world z) is across the line of
    sight: footprint sigma 40 / 5 * 0.5 = 4 px, radius ceil(3 sqrt(16.3)) = 13 px > 6 px: the anchor touches
    the image. Along the line of sight (anchor 1: world z for A, anchor 4: world y for B) it projects to a
    point: sigma 0.08 px, radius ceil(3 sqrt(0.0064 + 0.3)) = 2 px < 6 px: not visible. Anchors of the other
    camera are at depth 0."""
    cam_a, cam_b = _cameras()
    for name, model in _models().items():
        assert model.visible_anchors(cam_a).tolist() == [True, False, False, False, False], name
        assert model.visible_anchors(cam_b).tolist() == [False, False, True, True, False], name
    # the same anchors turned 90 degrees about x (y -> z): the verdicts follow the turned axes
    turned = torch.tensor([[1.0, 1.0, 0.0, 0.0]]).repeat(len(POS), 1)
    assert anchor_visibility(cam_a, POS, LIN, turned).tolist() == [True, True, False, False, False]


def test_every_family_prefilter_uses_the_first_three_linear_scales():
    """make_camera(): 64 x 48, f = 40, at z = -5 looking along +z. An anchor at (-4.625, 0, 0) (depth 5)
    projects to u = 32 + 40 * (-4.625) / 5 = -5 px, 5 px left of the image. Its footprint radius is
    ceil(3 sqrt(64 s^2 + 0.3)) px for an isotropic world scale s: 12 px for s = 0.5 (touches the image),
    2 px for s = 0.01 (does not). Anchor 0 has s = 0.5 in scales[:3] and 0.01 in scales[3:], anchor 1 the
    reverse: only anchor 0 is kept, whatever the family stores (log or linear scales)."""
    cam = make_camera()
    pos = torch.tensor([[-4.625, 0.0, 0.0], [-4.625, 0.0, 0.0]])
    lin = torch.tensor([[0.5] * 3 + [0.01] * 3, [0.01] * 3 + [0.5] * 3])
    want = [True, False]
    for name, model in models_at(pos, lin).items():  # Octree-GS: level 0 is always in the LOD set
        assert model.visible_anchors(cam).tolist() == want, name
    kw = {k: (v[:2] if torch.is_tensor(v) else v) for k, v in hac_kwargs(hac_files.K + 1).items()}
    raw = HACModel(voxel_size=0.001, **{**kw, "anchor": pos, "scaling": lin.log(), "decoded_version": False})
    assert raw.visible_anchors(cam).tolist() == want  # a raw HAC++ model stores log scales
    ref = NeuralGaussianModel(2, feat_dim=4, n_offsets=1)
    with torch.no_grad():
        ref._anchor.copy_(pos)
        ref._scaling.copy_(lin.log())
    assert ref.visible_anchors(cam).tolist() == want


# ------------------------------------------------------------------------------ decoded Gaussians
def _zero_odd_opacities(seq: nn.Sequential, k: int) -> None:
    """Last Linear of a Scaffold-family opacity decoder: output k is atanh(0.5) for even k and exactly 0 for
    odd k (tanh(0) = 0), for every anchor."""
    with torch.no_grad():
        seq[2].weight.zero_()
        seq[2].bias.copy_(torch.tensor([math.atanh(0.5) if i % 2 == 0 else 0.0 for i in range(k)]))


def test_every_family_drops_gaussians_whose_neural_opacity_is_exactly_zero():
    """Scaffold-GS (and every family after it) keeps a Gaussian only where neural opacity > 0."""
    cam = make_camera()
    even = lambda k: torch.arange(0, k, 2)  # noqa: E731
    ref = NeuralGaussianModel(3, feat_dim=4, n_offsets=4)
    _zero_odd_opacities(ref.mlp_opacity, 4)
    g = ref.decode(cam)
    assert torch.equal(g.offset_of, even(4).repeat(3)) and torch.allclose(g.opacities, torch.full((6,), 0.5))
    kw = hac_kwargs(hac_files.K + 1)
    kw["mask"] = torch.ones_like(kw["mask"])
    hac = HACModel(voxel_size=0.01, **kw)
    _zero_odd_opacities(hac.mlp_opacity, hac_files.K)
    assert torch.equal(hac.decode(cam).offset_of, even(hac_files.K).repeat(hac_files.A))
    octo = octree_files._model(octree_files._arrays(0), octree_files._decoders(torch.Generator().manual_seed(0)))
    _zero_odd_opacities(octo.mlp_opacity, octree_files.K)
    assert torch.equal(octo.decode(cam).offset_of, even(octree_files.K).repeat(octree_files.A))
    # CompGS: one opacity per coupled primitive; the skip path reads res_feat channel 0, zero for odd slots
    ca = compgs_files._arrays(0)
    res = torch.from_numpy(ca["res"]).clone()
    res[:, :, 0] = 1.0
    res[:, 1::2, 0] = 0.0
    comp = CompGSModel(means=torch.from_numpy(ca["means"]), scales_before_exp=torch.from_numpy(ca["scales"]),
                       ref_feats=torch.from_numpy(ca["ref"]), res_feats=res)
    op = comp.network.prediction_net.opacity_pred_mlp
    with torch.no_grad():
        op.net[-1].weight.zero_()
        op.net[-1].bias.zero_()
        op.skip.weight.zero_()
        op.skip.bias.zero_()
        op.skip.weight[0, compgs_files.C] = 1.0  # the first res_feat channel
    g = comp.decode(cam)
    assert torch.equal(g.offset_of, even(compgs_files.K).repeat(compgs_files.A))
    assert torch.allclose(g.opacities, torch.full_like(g.opacities, math.tanh(1.0)))


def test_assemble_gaussians_takes_an_overflowed_scaling_as_the_largest_float() -> None:
    k, r = 2, 3
    scaling = torch.ones(r, 6)
    scaling[1, 3:] = math.inf
    scale_rot = torch.randn(r * k, 7, requires_grad=True)
    g = assemble_gaussians(torch.arange(r), k, torch.zeros(r, 3), torch.zeros(r * k, 3), scaling, torch.ones(r * k),
                           torch.rand(r * k, 3), scale_rot, torch.ones(r * k, dtype=torch.bool))
    assert bool(torch.isfinite(g.scales).all())
    assert torch.equal(g.scales[2:4], torch.finfo(torch.float32).max * torch.sigmoid(scale_rot[2:4, :3]))
    assert torch.equal(g.scales[:2], torch.sigmoid(scale_rot[:2, :3]))  # finite scalings unchanged
    g.scales.sum().backward()
    assert scale_rot.grad is not None and bool(torch.isfinite(scale_rot.grad).all())


# ------------------------------------------------------------------------------ the models themselves
def test_every_family_model_is_frozen_in_eval_mode_with_one_opacity_per_anchor():
    """The family models are for evaluation (load_model_dir: "eval mode, frozen"): no parameter takes
    gradients, no module is in training mode. Scaffold-GS's anchor ``_opacity`` is ``[A, 1]`` (one PLY
    ``opacity`` column per anchor); CompGS keeps no anchor opacity."""
    for name, model in _models().items():
        assert len(list(model.parameters())) > 10, name  # the decoders' weights and biases
        assert [n for n, p in model.named_parameters() if p.requires_grad] == [], name
        assert [n for n, m in model.named_modules() if m.training] == [], name
        if name != "compgs":
            assert model._opacity.shape == (len(POS), 1), name


def test_family_models_refuse_a_tensor_of_another_anchor_count_or_trailing_size():
    for cls, kw, names in family_kwargs():
        cls(**kw)  # as built: accepted
        for i, name in enumerate(names):
            short = {**kw, name: kw[name][:-1]}
            # the first tensor sets A: the next one is named as disagreeing with it
            with pytest.raises(ShapeError, match=names[1] if i == 0 else name):
                cls(**short)
    # the fixed trailing sizes: positions 3, scales 6, offsets [K, 3], mask [M, 1], level [A, 1]
    for cls, kw, _ in family_kwargs():
        for name, bad in (("scaling", lambda x: x[:, :5]), ("scales_before_exp", lambda x: x[:, :5]),
                          ("anchor", lambda x: x[:, :2]), ("means", lambda x: x[:, :2]),
                          ("offset", lambda x: x[:, :, :2]), ("mask", lambda x: x[:, :, :1].repeat(1, 1, 2)),
                          ("level", lambda x: x.repeat(1, 2))):
            if name in kw:
                with pytest.raises(ShapeError, match=name):
                    cls(**{**kw, name: bad(kw[name])})


def test_abstract_bases_refuse_what_their_subclasses_must_define():
    base = AnchorModel()
    with pytest.raises(NotImplementedError):
        base.visible_anchors(make_camera())
    with pytest.raises(NotImplementedError):
        base.decode(make_camera())
    masked = MaskedAnchorModel(**hac_kwargs(hac_files.K + 1))
    with pytest.raises(NotImplementedError):
        masked.get_anchor  # noqa: B018 - the property is what is tested
    with pytest.raises(InputValueError, match=r"AnchorModel.decode got unknown option\(s\) \['x', 'y'\]"):
        base.refuse_options({"y": 1, "x": 2})
    base.refuse_options({})


def test_as_param_is_a_frozen_float32_copy_unless_asked():
    src = np.arange(6, dtype=np.float64).reshape(2, 3)
    p = as_param(src)
    assert isinstance(p, nn.Parameter) and p.dtype == torch.float32 and not p.requires_grad
    assert torch.equal(p, torch.arange(6.0).reshape(2, 3))
    assert as_param(np.zeros(2), requires_grad=True).requires_grad is True
    t = torch.ones(3)
    q = as_param(t, requires_grad=True)
    assert q.requires_grad and q.data_ptr() != t.data_ptr()  # a copy: the caller's tensor is not shared
    with torch.no_grad():
        q.add_(1.0)
    assert torch.equal(t, torch.ones(3))
    frozen = as_param(t)
    t[0] = 5.0
    assert frozen.tolist() == [1.0, 1.0, 1.0]  # a copy without gradients too
    # a non-contiguous array (a column slice) is read correctly
    assert torch.equal(as_param(src[:, 1]), torch.tensor([1.0, 4.0]))


