"""Small PSF banks for the optics tests: a tiny Gaussian bank and a synthetic bank with known, shift-variant kernels."""

from __future__ import annotations

import torch

from controlgs_adapter.downstream.optics.bank import PSFBank

D64 = torch.float64


def tiny_bank(**over):
    L, G, K = 3, 3, 5
    psf = torch.rand(L, G, G, K, K, dtype=D64)
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, 5, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    args = dict(psf=psf, psf_pitch_mm=torch.full((L, G, G), 0.1, dtype=D64), field_x=f, field_y=f,
                chief=torch.stack([cx, cy], -1).expand(L, 5, 5, 2).clone(), chief_x=c, chief_y=c,
                wavelengths_nm=(656.0, 550.0, 486.0), display_mm=(24.0, 24.0))
    args.update(over)
    return PSFBank(**args)


import torch

D64 = torch.float64


def synthetic_bank(K=7, G=4, L=2, pitch_px=1.0, width_px=16, uniform=True, identity=True, seed=0):
    """A small bank: random PSFs (the same everywhere if ``uniform``), identity or pincushion chief rays."""
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(L, G, G, K, K, generator=g, dtype=D64) ** 3
    if uniform:
        psf = psf[:1, :1, :1].expand(L, G, G, K, K).clone()
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, 9, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    scale = 1.0 if identity else 1 + 0.08 * (cx ** 2 + cy ** 2)
    chief = torch.stack([cx * scale, cy * scale], -1).expand(L, 9, 9, 2).clone()
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((L, G, G), pitch_px * 24 / width_px, dtype=D64), field_x=f,
                   field_y=f, chief=chief, chief_x=c, chief_y=c, wavelengths_nm=(600.0, 500.0)[:L],
                   display_mm=(24.0, 24.0))


def random_bank(L=3, G=3, K=5, pitch_mm=1.0, chief=None, C=9, seed=0, pincushion=0.0, flip_x=False):
    """A bank on a 24 x 24 mm display: seeded random PSFs (squared uniform noise) on a ``G x G`` field grid,
    pitch ``pitch_mm``; chief rays on a ``C x C`` grid, ``chief(d)`` per axis (default: the identity) times
    ``1 + pincushion r^2``, x mirrored if ``flip_x``; wavelengths the first ``L`` of 656 / 550 / 486 / 420 nm."""
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(L, G, G, K, K, dtype=D64, generator=g) ** 2
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, C, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    axis = chief or (lambda d: d)
    s = 1 + pincushion * (cx ** 2 + cy ** 2)
    x, y = axis(cx) * s, axis(cy) * s
    ch = torch.stack([-x if flip_x else x, y], -1).expand(L, C, C, 2).clone()
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((L, G, G), pitch_mm, dtype=D64), field_x=f, field_y=f, chief=ch,
                   chief_x=c, chief_y=c, wavelengths_nm=(656.0, 550.0, 486.0, 420.0)[:L], display_mm=(24.0, 24.0))


def affine_bank(a, b, axis=(0.0, 0.0), symmetric=False, C=9):
    """A 3-wavelength bank whose green (reference) chief rays are the affine map ``G(d) = a d + b`` (``a`` 2 x 2,
    ``b`` 2) on a ``C x C`` grid, red and blue the identity; ``meta.lens`` gives ``axis`` and ``symmetric``.
    Bilinear interpolation of an affine map is exact, so ``G`` is known everywhere."""
    bank = random_bank(L=3, C=C)
    c = torch.linspace(-1, 1, C, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    d = torch.stack([cx, cy], -1)
    chief = bank.chief.double().clone()
    chief[1] = d @ torch.as_tensor(a, dtype=D64).T + torch.as_tensor(b, dtype=D64)
    bank.chief = chief.float()
    bank.validate()
    bank.meta["lens"] = {"axis": list(axis), "rotationally_symmetric": symmetric, "psf": True, "kind": "prescription"}
    return bank


def radial_lens_bank(k=0.2, C=257, distance_mm=600.0, magnification=15.0, lens=None):
    """A traced-looking bank on a 24 x 24 mm display whose chief rays are the radial polynomial
    ``q = d (1 + k |d|^2)`` (every wavelength) on a ``C x C`` grid, with ``meta`` giving the virtual image
    at ``distance_mm`` and the reference ``magnification``: tan(angle) = q * 12 * magnification / distance_mm
    per axis. ``lens``: a ``meta["lens"]`` instead of the prescription (a distortion-profile bank)."""
    bank = random_bank(L=3, C=C)
    c = torch.linspace(-1, 1, C, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    s = 1 + k * (cx ** 2 + cy ** 2)
    bank.chief = torch.stack([cx * s, cy * s], -1).expand(3, C, C, 2).clone().float()
    if lens is None:
        bank.meta.update(prescription={"virtual_image_distance_mm": distance_mm, "display_mm": [24.0, 24.0]},
                         figures={"reference_magnification": magnification})
    else:
        bank.meta["lens"] = {"axis": [0.0, 0.0], "rotationally_symmetric": True, "psf": False, "kind": "profile", **lens}
    return bank
