"""Degenerate anchors (scales of 1e20, or a log-scale whose exp overflows float32) keep every adapter
gradient finite, equal to the float64 render without the splatter's spread cap."""

from __future__ import annotations

import copy
import math
from typing import Any

import pytest
import torch

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.backends.models.anchor_model import assemble_gaussians
from controlgs_adapter.rendering import splatter
from controlgs_adapter.rendering.protocol import render_view

STATE = RuntimeState(downsample=2.0, power_saving=0.4)


def _adapter_grads(model: Any, scene: Any, anchor: int, log_scale: float | None, dtype: torch.dtype,
                   ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Render test view 0 through a wrapped copy of ``model`` (anchor ``anchor``'s Gaussian log-scales set to
    ``log_scale``; its Gaussians get scales of about exp(log_scale)) and return the image and the gradients of a
    fixed weighted sum of it in every adapter tensor."""
    m = copy.deepcopy(model).to(dtype)
    if log_scale is not None:
        with torch.no_grad():
            m._scaling[anchor, 3:] = log_scale
    cgs = ControlGS.wrap(m)
    try:
        with torch.no_grad():
            for i, p in enumerate(cgs.injector.parameters()):
                p.copy_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(i), dtype=torch.float64))
        cam = scene.test_cameras[0]
        image = render_view(cgs, m, cam, STATE, scene.background.to(dtype))
        (image * torch.linspace(-1.0, 1.0, image.numel(), dtype=dtype).view_as(image)).sum().backward()
        return image.detach(), {n: p.grad.detach().clone() for n, p in cgs.injector.named_parameters()}
    finally:
        cgs.unwrap()


def _drawn_anchor(model: Any, scene: Any) -> int:
    """The anchor of the most opaque Gaussian the test view draws."""
    cam = scene.test_cameras[0]
    with torch.no_grad():
        g = model.decode(cam, model.visible_anchors(cam))
    return int(g.anchor_of[g.opacities.argmax()])


@pytest.mark.parametrize("log_scale", [math.log(1e20), 100.0])  # 100: exp overflows to inf in float32
def test_a_degenerate_anchor_keeps_every_adapter_gradient_finite(tiny: Any, log_scale: float,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    scene, model = tiny
    anchor = _drawn_anchor(model, scene)
    image, grads = _adapter_grads(model, scene, anchor, log_scale, torch.float32)
    assert bool(torch.isfinite(image).all())
    plain, _ = _adapter_grads(model, scene, anchor, None, torch.float32)
    assert float((image - plain).abs().max()) > 1e-3  # the degenerate Gaussians are drawn (a veil over the view)
    assert set(grads) >= {"conditions", "projections.lens.d8.weight", "projections.display.d8.weight"}
    for name, grad in grads.items():
        assert bool(torch.isfinite(grad).all()), name
        assert float(grad.abs().max()) > 0.0, name
    # the reference: float64 (scales up to ~1e75 representable there) without the spread cap
    monkeypatch.setattr(splatter, "MAX_SPREAD", math.inf)
    monkeypatch.setattr(splatter, "_MAX_SPREAD_PX", math.inf)
    ref_image, ref_grads = _adapter_grads(model, scene, anchor, log_scale, torch.float64)
    torch.testing.assert_close(image.double(), ref_image, rtol=0, atol=1e-5)
    for name, grad in grads.items():
        err = float((grad.double() - ref_grads[name]).norm() / ref_grads[name].norm())
        assert err < 1e-4, (name, err)


def test_without_the_cap_the_float32_adapter_gradients_are_nan(tiny: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """What the cap prevents (the adversarial finding): NaN in every adapter tensor from one anchor."""
    scene, model = tiny
    anchor = _drawn_anchor(model, scene)
    monkeypatch.setattr(splatter, "MAX_SPREAD", math.inf)
    monkeypatch.setattr(splatter, "_MAX_SPREAD_PX", math.inf)
    _, grads = _adapter_grads(model, scene, anchor, math.log(1e20), torch.float32)
    assert all(not bool(torch.isfinite(g).all()) for g in grads.values())


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


import helpers.compgs_files as compgs_t
import helpers.contextgs_files as contextgs_t
import helpers.hac_files as hac_t
import helpers.octree_files as octree_t
import numpy as np
from helpers.contextgs_files import PAD, A, _arrays, _decoders
from helpers.family_checks import make_camera
from torch import nn

from controlgs_adapter import Camera
from controlgs_adapter.backends.compgs import CompGSModel
from controlgs_adapter.backends.contextgs import ContextGSModel
from controlgs_adapter.backends.hac import HACModel
from controlgs_adapter.backends.octree_gs import OctreeGSModel
from controlgs_adapter.errors import InputValueError


def test_prefilter_uses_anchor_zero_rotation():
    """ContextGS's prefilter_voxel passes rotations[[0]] for every anchor; the stand-in does the same
    (kept from the file's row 0 even when that anchor is dropped)."""
    from helpers.family_checks import make_camera

    from controlgs_adapter.backends.models.anchor_model import anchor_visibility

    arr = _arrays(9, decoded=True)
    arr["anchor"][: A - PAD] = np.array([[0.5, 0.0, 0.0]], np.float32) + np.arange(A - PAD, dtype=np.float32)[:, None] * \
        np.array([[0.01, 0.0, 0.0]], np.float32)  # centres 8-15 px beyond the right edge of the image
    arr["scale"][: A - PAD] = np.array([0.01, 0.2, 0.01, 0.1, 0.1, 0.1], np.float32)  # long along y
    t = {k: torch.from_numpy(v) for k, v in arr.items()}
    half = 2 ** -0.5
    rot = torch.tensor([[half, half, 0.0, 0.0]]).repeat(A, 1)  # 90 degrees about x: long along the view axis
    rot[0] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    model = ContextGSModel(anchor=t["anchor"], offset=t["offset"], mask=t["mask"][:, :, None], anchor_feat=t["feat"],
                           scaling=t["scale"], hyper_latent=t["hyper"], rotation=rot, decoded_version=True, **_decoders(9))
    cam = make_camera()
    cam.intrinsics[0, 0] = cam.intrinsics[1, 1] = 400.0  # narrow: a long axis along the view projects short
    got = model.visible_anchors(cam)
    own = anchor_visibility(cam, model.get_anchor, model.get_scaling[:, :3], rot)
    first = anchor_visibility(cam, model.get_anchor, model.get_scaling[:, :3], rot[:1].expand(A, 4))
    assert torch.equal(got, first) and not torch.equal(got, own)
    assert got[1 : A - PAD].all() and not own[1 : A - PAD].any()  # anchor 0's footprint reaches into the image


def test_as_param_default_frozen_float32():
    from controlgs_adapter.backends.models.anchor_model import as_param

    p = as_param(np.arange(3, dtype=np.float64))
    assert p.dtype == torch.float32 and p.requires_grad is False and p.tolist() == [0.0, 1.0, 2.0]
    assert as_param(np.zeros(2), requires_grad=True).requires_grad is True
    src = torch.ones(2)
    q = as_param(src)
    src[0] = 5.0
    assert q.tolist() == [1.0, 1.0]  # a copy


def _cameras() -> tuple[Camera, Camera]:
    """Two cameras at the origin, f = 40, 64 x 48, principal point (-6, 24): a point on the optical axis
    projects 6 px left of the image. A looks along world +z; B along world +y (camera axes: x = world x,
    y = -world z, z = world y)."""
    k = torch.tensor([[40.0, 0.0, -6.0], [0.0, 40.0, 24.0], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4)
    w2c[1:3, 1:3] = torch.tensor([[0.0, -1.0], [1.0, 0.0]])
    return Camera(torch.eye(4), k, 64, 48), Camera(w2c, k, 64, 48)


#: anchors 0-1 on camera A's optical axis (depth 5), 2-4 on camera B's; each has one scale 0.5 and two 0.01
_POS = torch.tensor([[0.0, 0, 5], [0, 0, 5], [0, 5, 0], [0, 5, 0], [0, 5, 0]])


_LIN = torch.tensor([[0.5, 0.01, 0.01], [0.01, 0.01, 0.5], [0.5, 0.01, 0.01], [0.01, 0.01, 0.5], [0.01, 0.5, 0.01]])


#: With the identity rotation (what a family's file without rot_* means: CompGS's decoder resets rotations to
#: identity) the long axis of anchors 0, 2 (world x) and 3 (world z) is across the line of sight: footprint
#: sigma 40 / 5 * 0.5 = 4 px, radius ceil(3 sqrt(16.3)) = 13 px > 6 px: the anchor touches the image. Along
#: the line of sight (anchor 1: world z for A, anchor 4: world y for B) it projects to a point: sigma 0.08 px,
#: radius ceil(3 sqrt(0.0064 + 0.3)) = 2 px < 6 px: not visible. Anchors of the other camera are at depth 0.
_WANT_A, _WANT_B = [True, False, False, False, False], [False, False, True, True, False]


def _stand_ins_without_rotation() -> dict[str, object]:
    n, lin = len(_POS), torch.cat([_LIN, torch.full((len(_POS), 3), 0.02)], dim=1)
    ca = compgs_t._arrays(0)
    comp = CompGSModel(means=_POS, scales_before_exp=lin.log(), ref_feats=torch.from_numpy(ca["ref"][:n]),
                       res_feats=torch.from_numpy(ca["res"][:n]))
    ha = hac_t._arrays(0, decoded=True, mask_cols=hac_t.K + 1, n=n)
    hac = HACModel(voxel_size=0.001, decoded_version=True, anchor=_POS, offset=torch.from_numpy(ha["offset"]),
                   mask=torch.ones(n, hac_t.K + 1, 1), anchor_feat=torch.from_numpy(ha["feat"]), scaling=lin,
                   **hac_t._decoders(0))
    xa = {k: torch.from_numpy(v[:n]) for k, v in contextgs_t._arrays(0, decoded=True).items()}
    ctx = ContextGSModel(anchor=_POS, offset=xa["offset"], mask=torch.ones(n, contextgs_t.K, 1), anchor_feat=xa["feat"],
                         scaling=lin, hyper_latent=xa["hyper"], decoded_version=True, **contextgs_t._decoders(0))
    oa = octree_t._arrays(0)
    octo = OctreeGSModel(anchor=_POS, offset=torch.from_numpy(oa["offset"][:n]), anchor_feat=torch.from_numpy(oa["feat"][:n]),
                         scaling=lin.log(), level=torch.zeros(n, 1, dtype=torch.int32), extra_level=torch.zeros(n),
                         voxel_size=0.1, standard_dist=3.0, **octree_t._decoders(torch.Generator().manual_seed(0)))
    return {"compgs": comp, "hac": hac, "contextgs": ctx, "octree_gs": octo}


def test_stand_ins_without_rotations_prefilter_with_the_identity_rotation():
    cam_a, cam_b = _cameras()
    for name, model in _stand_ins_without_rotation().items():
        assert model.visible_anchors(cam_a).tolist() == _WANT_A, name
        assert model.visible_anchors(cam_b).tolist() == _WANT_B, name
    # the same anchors turned 90 degrees about x (y -> z): the verdicts follow the turned axes
    from controlgs_adapter.backends.models.anchor_model import anchor_visibility

    turned = torch.tensor([[1.0, 1.0, 0.0, 0.0]]).repeat(len(_POS), 1)
    assert anchor_visibility(cam_a, _POS, _LIN, turned).tolist() == [True, True, False, False, False]


def _hac_kw(n_mask_cols: int, seed: int = 0) -> dict:
    arr = hac_t._arrays(seed, decoded=True, mask_cols=n_mask_cols)
    return dict(anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                mask=torch.from_numpy(arr["mask"])[:, :, None], anchor_feat=torch.from_numpy(arr["feat"]),
                scaling=torch.from_numpy(arr["scale"]), decoded_version=True, **hac_t._decoders(seed))


def test_abstract_bases_refuse_what_their_subclasses_must_define():
    from controlgs_adapter.backends.hac import MaskedAnchorModel
    from controlgs_adapter.backends.models.anchor_model import AnchorModel

    base = AnchorModel()
    with pytest.raises(NotImplementedError):
        base.visible_anchors(make_camera())
    with pytest.raises(NotImplementedError):
        base.decode(make_camera())
    masked = MaskedAnchorModel(**_hac_kw(hac_t.K + 1))
    with pytest.raises(NotImplementedError):
        masked.get_anchor  # noqa: B018 - the property is what is tested
    with pytest.raises(InputValueError, match=r"AnchorModel.decode got unknown option\(s\) \['x', 'y'\]"):
        base.refuse_options({"y": 1, "x": 2})
    base.refuse_options({})


def test_as_param_is_a_frozen_float32_copy_unless_asked():
    from controlgs_adapter.backends.models.anchor_model import as_param

    src = np.arange(6, dtype=np.float64).reshape(2, 3)
    p = as_param(src)
    assert isinstance(p, nn.Parameter) and p.dtype == torch.float32 and not p.requires_grad
    assert torch.equal(p, torch.arange(6.0).reshape(2, 3))
    t = torch.ones(3)
    q = as_param(t, requires_grad=True)
    assert q.requires_grad and q.data_ptr() != t.data_ptr()  # a copy: the caller's tensor is not shared
    with torch.no_grad():
        q.add_(1.0)
    assert torch.equal(t, torch.ones(3))
    # a non-contiguous array (a column slice) is read correctly
    assert torch.equal(as_param(src[:, 1]), torch.tensor([1.0, 4.0]))


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
