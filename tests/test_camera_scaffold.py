"""Camera.from_scaffold against an independent computation: 3DGS's projection matrix and its NDC ->
pixel map, and the camera's ``uid`` picking the appearance code of a model with appearance_dim > 0."""

from __future__ import annotations

import math
import types

import pytest
import torch

from controlgs_adapter import Camera
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.errors import InputValueError


def _scaffold_camera(w: int, h: int, fovx: float, fovy: float, uid: int | None = 3) -> types.SimpleNamespace:
    """A 3DGS/Scaffold-GS camera as its ``Camera`` class builds it: ``world_view_transform`` the
    transposed world-to-camera, ``full_proj_transform`` = view @ projection (row-vector convention)."""
    angle = 0.3
    r = torch.tensor([[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0], [-math.sin(angle), 0.0, math.cos(angle)]],
                     dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3], w2c[:3, 3] = r, torch.tensor([0.2, -0.1, 3.0], dtype=torch.float64)
    znear, zfar = 0.01, 100.0
    top, right = math.tan(fovy / 2) * znear, math.tan(fovx / 2) * znear
    p = torch.zeros(4, 4, dtype=torch.float64)  # 3DGS getProjectionMatrix (symmetric frustum)
    p[0, 0], p[1, 1] = 2 * znear / (2 * right), 2 * znear / (2 * top)
    p[3, 2], p[2, 2], p[2, 3] = 1.0, zfar / (zfar - znear), -(zfar * znear) / (zfar - znear)
    view = w2c.T
    cam = types.SimpleNamespace(world_view_transform=view.float(), full_proj_transform=(view @ p.T),
                                image_width=w, image_height=h, FoVx=fovx, FoVy=fovy)
    if uid is not None:
        cam.uid = uid
    return cam


@pytest.mark.parametrize("w, h", [(64, 48), (63, 37)])
def test_projection_matches_3dgs_ndc_to_pixel(w, h):
    vc = _scaffold_camera(w, h, 1.1, 0.9)
    cam = Camera.from_scaffold(vc)
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.4, -0.3, 0.5], [-0.5, 0.2, -0.4]], dtype=torch.float64)
    hom = torch.cat([pts, torch.ones(3, 1, dtype=torch.float64)], dim=1) @ vc.full_proj_transform
    ndc = hom[:, :3] / hom[:, 3:]
    # 3DGS's ndc2Pix puts pixel centres at integers: ((ndc + 1) * S - 1) / 2; this library at i + 0.5
    want = torch.stack([((ndc[:, 0] + 1) * w - 1) / 2 + 0.5, ((ndc[:, 1] + 1) * h - 1) / 2 + 0.5], dim=1)
    uv, depth = cam.project(pts.float())
    assert torch.allclose(uv.double(), want, atol=2e-4, rtol=0)
    assert (depth > 0).all()
    assert cam.intrinsics[0, 2].item() == w / 2 and cam.intrinsics[1, 2].item() == h / 2
    fx = w / (2 * math.tan(1.1 / 2))
    assert cam.intrinsics[0, 0].item() == pytest.approx(fx, rel=1e-6)


def test_uid_carried_and_picks_the_appearance_code():
    vc = _scaffold_camera(32, 24, 1.0, 0.8, uid=3)
    cam = Camera.from_scaffold(vc)
    assert cam.extra == {"uid": 3}
    assert Camera.from_scaffold(_scaffold_camera(32, 24, 1.0, 0.8, uid=None)).extra == {}
    with pytest.raises(InputValueError, match="uid"):
        Camera.from_scaffold(_scaffold_camera(32, 24, 1.0, 0.8, uid=-1))
    torch.manual_seed(0)
    model = NeuralGaussianModel(6, feat_dim=8, n_offsets=2, appearance_dim=4, num_cameras=5)
    with torch.no_grad():
        model._anchor.copy_(torch.randn(6, 3) * 0.3)
        model._anchor_feat.copy_(torch.randn(6, 8))
        model.embedding_appearance.embedding.weight.copy_(torch.randn(5, 4) * 3)
        model.mlp_opacity[2].bias.fill_(5.0)  # every Gaussian kept
    want = model.decode(Camera(cam.world_to_camera, cam.intrinsics, 32, 24, {"uid": 3})).colors
    code0 = model.decode(Camera(cam.world_to_camera, cam.intrinsics, 32, 24)).colors
    got = model.decode(cam).colors
    assert torch.equal(got, want)
    assert (got - code0).abs().max() > 1e-2  # the code matters: uid 0 would decode other colours


def test_scaled_rescales_each_axis_by_its_own_rounded_size():
    """Camera.scaled(f): size round(size / f) per axis, K's rows scaled by that axis's ratio (a 64 x 48
    camera at f = 3 becomes 21 x 16: x by 21/64, y by 16/48, not the same factor)."""
    k = torch.tensor([[50.0, 0.0, 32.0], [0.0, 40.0, 24.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cam = Camera(torch.eye(4, dtype=torch.float64), k, 64, 48, {"uid": 2})
    small = cam.scaled(3.0)
    assert (small.width, small.height, small.extra) == (21, 16, {"uid": 2})
    want = torch.tensor([[50.0 * 21 / 64, 0.0, 32.0 * 21 / 64], [0.0, 40.0 * 16 / 48, 24.0 * 16 / 48], [0.0, 0.0, 1.0]],
                        dtype=torch.float64)
    assert torch.allclose(small.intrinsics, want, atol=1e-12, rtol=0)
    corner = torch.tensor([[0.64, 0.6, 1.0]], dtype=torch.float64)  # projects to pixel (64, 48): the corner
    assert torch.allclose(cam.project(corner)[0], torch.tensor([[64.0, 48.0]], dtype=torch.float64))
    assert torch.allclose(small.project(corner)[0], torch.tensor([[21.0, 16.0]], dtype=torch.float64))
