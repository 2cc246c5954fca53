"""Float64 references for the anchor families' decoding and prefilter, written from the families' published
code, evaluated one anchor and one offset at a time from raw weights (no library code)."""

from __future__ import annotations

import math

import torch
from torch import nn

from controlgs_adapter import Camera
from controlgs_adapter.backends.compgs import ResidualBlock, ResidualMLP

D = torch.float64


def oblique_camera(uid: int | None = None) -> Camera:
    """A 72 x 40 camera about 5 units from the origin, turned 0.1 rad about y, with different focal lengths
    and its principal point off centre; ``uid`` in ``extra`` when given."""
    c, s = math.cos(0.1), math.sin(0.1)
    w2c = torch.eye(4)
    w2c[:3, :3] = torch.tensor([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])
    w2c[:3, 3] = torch.tensor([-0.3, 0.2, 5.0])
    k = torch.tensor([[52.0, 0.0, 37.0], [0.0, 47.0, 21.0], [0.0, 0.0, 1.0]])
    return Camera(w2c, k, 72, 40, {} if uid is None else {"uid": uid})


def camera_centre(cam: Camera) -> torch.Tensor:
    """The camera centre -R^T t in float64, from the world-to-camera matrix."""
    w2c = cam.world_to_camera.to(D)
    return -(w2c[:3, :3].T @ w2c[:3, 3])


def mlp(d_in: int, d_hidden: int, d_out: int, tail: nn.Module | None) -> nn.Sequential:
    """A Scaffold-family decoder: Linear, ReLU, Linear, then ``tail`` if given."""
    return nn.Sequential(nn.Linear(d_in, d_hidden), nn.ReLU(), nn.Linear(d_hidden, d_out), *([tail] if tail else []))


def mlp64(mod: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """``mod`` evaluated layer by layer in float64 from its weights (Linear, ReLU, LeakyReLU, Tanh, Sigmoid,
    Softmax over dim 1, Identity, Sequential, CompGS's ResidualBlock / ResidualMLP)."""
    if isinstance(mod, nn.Sequential):
        for layer in mod:
            x = mlp64(layer, x)
        return x
    if isinstance(mod, nn.Linear):
        return x @ mod.weight.detach().to(D).T + mod.bias.detach().to(D)
    if isinstance(mod, nn.ReLU):
        return torch.where(x > 0, x, torch.zeros_like(x))
    if isinstance(mod, nn.LeakyReLU):
        return torch.where(x > 0, x, 0.01 * x)
    if isinstance(mod, nn.Tanh):
        return (torch.exp(x) - torch.exp(-x)) / (torch.exp(x) + torch.exp(-x))
    if isinstance(mod, nn.Sigmoid):
        return 1.0 / (1.0 + torch.exp(-x))
    if isinstance(mod, nn.Softmax):
        e = torch.exp(x - x.max(dim=1, keepdim=True).values)
        return e / e.sum(dim=1, keepdim=True)
    if isinstance(mod, ResidualBlock):
        return x + mlp64(mod.net, x)
    if isinstance(mod, ResidualMLP):
        skip = x if isinstance(mod.skip, nn.Identity) else mlp64(mod.skip, x)
        return mlp64(mod.tail_activation, mlp64(mod.net, x) + skip)
    if isinstance(mod, nn.Identity):
        return x
    raise TypeError(type(mod))


def feature_bank64(feat: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Scaffold-GS's feature bank for one anchor: channel c mixes feat[4*(c mod F/4)], feat[2*(c mod F/2)]
    and feat[c] with the softmax weights w[0], w[1], w[2]."""
    f = feat.shape[0]
    c = torch.arange(f)
    return feat[4 * (c % (f // 4))] * w[0] + feat[2 * (c % (f // 2))] * w[1] + feat * w[2]


def gaussian64(anchor, offset, s, opacity, color, cov) -> dict[str, torch.Tensor]:
    """One Scaffold-family Gaussian: mean = anchor + offset * s[:3], scale = s[3:] * sigmoid(cov[:3]),
    rotation = cov[3:7] / |cov[3:7]|."""
    return {"means": anchor + offset * s[:3], "scales": s[3:] / (1.0 + torch.exp(-cov[:3])),
            "rotations": cov[3:7] / cov[3:7].norm(), "colors": color, "opacity": opacity}


def assert_gaussians(got, expected: dict[tuple[int, int], dict[str, torch.Tensor]]) -> None:
    """``got`` (NeuralGaussians) holds exactly the (anchor, offset) pairs of ``expected``, with its values."""
    pairs = [(int(a), int(k)) for a, k in zip(got.anchor_of, got.offset_of)]
    assert sorted(pairs) == sorted(expected)
    for g, key in enumerate(pairs):
        e = expected[key]
        for name in ("means", "scales", "rotations", "colors"):
            torch.testing.assert_close(getattr(got, name)[g].to(D), e[name], rtol=1e-5, atol=1e-6, msg=f"{name} {key}")
        torch.testing.assert_close(got.opacities[g].to(D), e["opacity"], rtol=1e-5, atol=1e-6)


def visible64(cam: Camera, means: torch.Tensor, scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """3DGS's prefilter in float64, anchor by anchor: depth > 0.2 and the square of half-width
    ceil(3 sqrt(lambda_max)) about the projected centre overlaps [0, W] x [0, H]; 2D covariance
    J W R S^2 R^T W^T J^T + 0.3 I with J at x/z, y/z clamped to 1.3 x the field of view."""
    w2c = cam.world_to_camera.to(D)
    k = cam.intrinsics.to(D)
    out = torch.zeros(means.shape[0], dtype=torch.bool)
    for i in range(means.shape[0]):
        t = w2c[:3, :3] @ means[i].to(D) + w2c[:3, 3]
        if t[2] <= 0.2:
            continue
        w, x, y, z = (quats[i].to(D) / quats[i].to(D).norm()).tolist()
        r = torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                          [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                          [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], dtype=D)
        cov3 = r @ torch.diag(scales[i].to(D) ** 2) @ r.T
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        # x/z, y/z clamped to the image widened by 15 % of its size on each side (3DGS's 1.3 x FoV)
        tx = min(max(float(t[0] / t[2]), -float(cx + 0.15 * cam.width) / fx), float(1.15 * cam.width - cx) / fx)
        ty = min(max(float(t[1] / t[2]), -float(cy + 0.15 * cam.height) / fy), float(1.15 * cam.height - cy) / fy)
        j = torch.tensor([[fx / t[2], 0, -fx * tx / t[2]], [0, fy / t[2], -fy * ty / t[2]]], dtype=D)
        m = j @ w2c[:3, :3]
        c2 = m @ cov3 @ m.T + 0.3 * torch.eye(2, dtype=D)
        det = c2[0, 0] * c2[1, 1] - c2[0, 1] ** 2
        mid = 0.5 * (c2[0, 0] + c2[1, 1])
        radius = math.ceil(3.0 * math.sqrt(mid + math.sqrt(max(float(mid * mid - det), 0.1))))
        u, v = fx * t[0] / t[2] + k[0, 2], fy * t[1] / t[2] + k[1, 2]
        out[i] = bool(det > 0 and u + radius > 0 and u - radius < cam.width and v + radius > 0 and v - radius < cam.height)
    return out
