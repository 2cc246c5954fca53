"""Fitting the learned lens pre-warp (paper Supp. "Lens Correction Through Pre-Warping").

The paper trains the pre-warp MLP end to end through the display-optics path with the 3DGS image
loss (10,000 iterations, learning rate 1e-3) and then bakes it into a lookup table:

    pipe = Pipeline.from_config({"lens": LensPrewarp.learned(), "optics": {"mode": "distortion"}})
    losses = fit_prewarp(pipe, images, targets)
    pipe.stages[pipe.names.index("lens")] = pipe["lens"].bake((H, W))   # or save_lut(...)

Only the lens stage's parameters are optimised; everything else in the pipeline is fixed.

:func:`fit_bank_prewarp` makes the default correction for a PSF bank: per display primary a map
and a gain over the whole display, fitted through the optics operator itself (any mode and
radiometry the optics stage has), and stored as a :class:`~.lens.DisplayLUTMap`:

- map: each display pixel shows the image at the *centroid* of its light in the eye, measured
  through the operator by its adjoint, ``c(p) = (A^T x)(p) / (A^T 1)(p)`` (``x`` the eye
  coordinate images). In ``"distortion"`` mode this is the chief ray; with PSFs it includes each
  PSF's centroid offset (coma: 0.55-0.60 px at (0.85, 0.85) at 256 px).
- gain: the per-pixel, per-primary scale ``g`` with ``(A g)(c(p)) = 1``: a flat field comes back
  flat. Solved by the fixed-point iteration ``g <- g / (A g)(c(p))``.

For an image that varies slowly on the scale of the PSFs, these two conditions are where the
image loss (L1, L2, SSIM) between eye and ground truth has its minimum (to first order in the
image's gradient: the eye sees ``I(c(p)) (A g)``), which is what the paper's MLP is trained to
approach with the 3DGS loss; here they are met directly, per display pixel, with no MLP.
"""

from __future__ import annotations

import copy
import time
from typing import TYPE_CHECKING, Callable, Sequence

import torch
import torch.nn.functional as F

from controlgs_adapter.checks import check_image, check_tensor
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.losses import LossWeights, image_loss
from controlgs_adapter.state import RuntimeState

from .bank_maps import DisplayLUTMap, _optics_bank, _optics_placement, bank_fingerprint
from .color import primaries_to_rgb_matrix, rgb_to_primaries_matrix
from .pipeline import Pipeline
from .stage import StageContext
from .warp import _interp_regular, chief_ray_grid, pixel_grid

if TYPE_CHECKING:  # pragma: no cover
    from .optics.bank import PSFBank

__all__ = ["fit_prewarp", "fit_bank_prewarp", "PREWARP_LOSS", "FIT_SIZES"]

#: Display sizes (pixels along the shorter side) :func:`fit_bank_prewarp` fits a table at by default.
FIT_SIZES: tuple[int, ...] = (64, 96, 128, 192, 256)

#: The 3DGS loss the paper names for the pre-warp: 0.8 L1 + 0.2 (1 - SSIM).
PREWARP_LOSS = LossWeights(l1=0.8, ssim=0.2, mse=0.0)


def fit_prewarp(
    pipeline: Pipeline,
    images: torch.Tensor,
    targets: torch.Tensor | None = None,
    *,
    state: RuntimeState = RuntimeState(),
    steps: int = 10_000,
    lr: float = 1e-3,
    weights: LossWeights = PREWARP_LOSS,
    generator: torch.Generator | None = None,
) -> list[float]:
    """Train the pipeline's ``"lens"`` stage so that the eye image matches the target.

    Args:
        pipeline: a pipeline with a trainable ``lens`` stage (e.g. ``LensPrewarp.learned()``) and
            the optics it must compensate.
        images: ``[N, 3, H, W]`` sRGB inputs at the native size (renders, or the ground truth
            itself for a pure lens calibration).
        targets: ``[N, 3, H, W]`` sRGB images the eye should see; default ``images``.
        state: run-time state during the fit.
        steps: optimiser steps, one image each (drawn with ``generator``).
        lr: Adam learning rate.
        weights: image-loss weights (default :data:`PREWARP_LOSS`).
    Returns:
        The loss of every step.
    """
    if "lens" not in pipeline:
        raise InputValueError(f"pipeline has no 'lens' stage to fit (stages: {pipeline.names})")
    params = [p for p in pipeline["lens"].parameters() if p.requires_grad]
    if not params:
        raise InputValueError("the pipeline's lens stage has no trainable parameters (use LensPrewarp.learned())")
    b = check_image("images", images)
    check_tensor("images", images, ["N", 3, "H", "W"])
    if targets is None:
        targets = images
    check_tensor("targets", targets, [images.shape[0], 3, b["H"], b["W"]], dtypes=(images.dtype,))
    if steps < 1 or not lr > 0:
        raise InputValueError(f"steps must be >= 1 and lr > 0, got steps={steps!r}, lr={lr!r}")
    optimizer = torch.optim.Adam(params, lr=lr)
    was_training = pipeline.training
    pipeline.train()
    losses: list[float] = []
    try:
        for _ in range(steps):
            i = int(torch.randint(images.shape[0], (1,), generator=generator))
            eye = pipeline(images[i], state, reference=targets[i])
            loss = image_loss(eye, targets[i], weights)
            optimizer.zero_grad()  # set_to_none=True: the default of every torch >= 2.0
            loss.backward()
            optimizer.step()
            losses.append(float(loss.detach()))
    finally:
        pipeline.train(was_training)
    return losses


def _primaries_operator(optics: torch.nn.Module, size: tuple[int, int], dtype: torch.dtype) -> Callable[[torch.Tensor], torch.Tensor]:
    """The optics stage as a linear operator on primary intensities ``[B, 3, H, W]`` -> ``[B, 3, H, W]``
    (the stage works on linear RGB and converts to the primaries itself; converting around it is
    exact to rounding)."""
    to_p, to_rgb = rgb_to_primaries_matrix(dtype), primaries_to_rgb_matrix(dtype)
    ctx = StageContext(native_size=size)

    def op(s: torch.Tensor) -> torch.Tensor:
        rgb = torch.einsum("ij,bjhw->bihw", to_rgb, s)
        return torch.einsum("ij,bjhw->bihw", to_p, optics(rgb, RuntimeState(), ctx))

    return op


def _fill_invalid(values: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Extend ``values`` ``[C, H, W, D]`` from the ``valid`` ``[C, H, W]`` pixels into the others by
    repeated 3x3 averaging of valid neighbours (a smooth nearest-valid continuation). Refused when a
    channel has no valid pixel (there is nothing to continue from)."""
    c, h, w, d = values.shape
    empty = (~valid.reshape(c, -1).any(1)).nonzero().flatten().tolist()
    if empty:
        raise InputValueError(f"no display pixel could be measured through the optics (none for primary channel(s) {empty} "
                              f"of {c}: their light leaves the eye frame everywhere)")
    v = torch.where(valid[..., None], values, torch.zeros_like(values)).permute(0, 3, 1, 2).reshape(1, c * d, h, w)
    m = valid[:, None].expand(c, d, h, w).reshape(1, c * d, h, w).to(values.dtype)
    kernel = torch.ones(c * d, 1, 3, 3, dtype=values.dtype)
    while not bool(m.all()):  # each channel has a valid pixel: every round grows it
        s = F.conv2d(v, kernel, padding=1, groups=c * d)
        n = F.conv2d(m, kernel, padding=1, groups=c * d)
        grow = (m == 0) & (n > 0)
        v = torch.where(grow, s / n.clamp(min=1), v)
        m = torch.where(grow, torch.ones_like(m), m)
    return v.reshape(c, d, h, w).permute(0, 2, 3, 1)


def _psf_centroids(bank: "PSFBank", p: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Centroid offsets from the chief ray ``[3, H, W, 2]`` (display-normalised) of the bank's PSFs at
    display points ``p`` ``[H, W, 2]``: the field PSFs' first moments, bilinear over the field grid
    and constant beyond its outer samples (as the operators blend the PSFs)."""
    psf = bank.psf.to(dtype)  # [L, Gy, Gx, K, K]
    k = psf.shape[-1]
    taps = torch.arange(k, dtype=dtype) - k // 2
    pitch = bank.psf_pitch_mm.to(dtype)
    mx = (psf.sum(-2) * taps).sum(-1) * pitch / (bank.display_mm[0] / 2)  # [L, Gy, Gx] x moment
    my = (psf.sum(-1) * taps).sum(-1) * pitch / (bank.display_mm[1] / 2)
    moments = torch.stack([mx, my], -1)  # [L, Gy, Gx, 2]
    fx, fy = bank.field_x.to(dtype), bank.field_y.to(dtype)
    q = torch.stack([p[..., 0].clamp(float(fx[0]), float(fx[-1])), p[..., 1].clamp(float(fy[0]), float(fy[-1]))], -1)
    if min(moments.shape[1:3]) < 2:
        return moments.mean((1, 2))[:, None, None].expand(-1, *p.shape[:2], -1)
    return _interp_regular(moments, q.expand(3, -1, -1, -1), (float(fx[0]), float(fx[-1])), (float(fy[0]), float(fy[-1])))


def _reach(mode: str, bank: "PSFBank", p: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """How far ``[3, H, W]`` (display-normalised) the light of the display pixels at ``p`` ``[H, W, 2]``
    spreads in the eye: 3 pixels in ``"distortion"`` mode; else 1.5 x the half-width ``K // 2 + 0.5``
    of the PSF window at its (bilinear) sample pitch (room for the blend of neighbouring fields)."""
    h, w = p.shape[:2]
    if mode == "distortion":
        return torch.full((3, h, w), 3.0 / min(h, w), dtype=dtype)  # a footprint: a few pixels
    pitch = bank.psf_pitch_mm.to(dtype)[..., None]  # [3, Gy, Gx, 1]
    spans = ((float(bank.field_x[0]), float(bank.field_x[-1])), (float(bank.field_y[0]), float(bank.field_y[-1])))
    pitch = _interp_regular(pitch, p.expand(3, -1, -1, -1), *spans)[..., 0] if min(pitch.shape[1:3]) > 1 else pitch.amax()
    half_mm = min(bank.display_mm) / 2
    return 1.5 * pitch * (bank.psf.shape[-1] // 2 + 0.5) / half_mm


def _fit_mode(optics: torch.nn.Module, bank: "PSFBank", size: tuple[int, int], gain_iterations: int,
              dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, dict[str, float]]:
    """One optics mode: ``(displacement [3, H, W, 2], gain [3, H, W], residuals)`` over the display."""
    h, w = size
    op = _primaries_operator(optics, size, dtype)
    p = pixel_grid(size, dtype)  # [H, W, 2] display-normalised (the fit image spans the display)
    # centroids through the adjoint: A^T applied to the eye images x, y and 1
    x = torch.zeros(3, 3, h, w, dtype=dtype, requires_grad=True)
    probes = torch.stack([p[..., 0].expand(3, h, w), p[..., 1].expand(3, h, w), torch.ones(3, h, w, dtype=dtype)])
    (adj,) = torch.autograd.grad(op(x), x, probes)  # [3 probes, 3 primaries, H, W]
    chief, _ = chief_ray_grid(bank.chief.to(dtype), size, sample_x=bank.chief_x, sample_y=bank.chief_y)  # [3, H, W, 2]
    reach = _reach(str(optics.mode), bank, p, dtype)
    throughput = adj[2]
    centroid = torch.stack([adj[0], adj[1]], -1) / throughput.clamp(min=1e-12)[..., None]
    limit = 1.0 - 1.0 / min(h, w)
    valid = (throughput > 1e-6) & ((chief.abs() + reach[..., None]) < limit).all(-1)
    # where the frame cuts a pixel's light, continue the measured discretisation residual beyond
    # the bank's own centroid offsets (the PSFs' first moments, blended as the operator blends them)
    model = chief if optics.mode == "distortion" else chief + _psf_centroids(bank, p, dtype)
    target = (model + _fill_invalid(centroid - model, valid)).detach()  # [3, H, W, 2] eye position of every display pixel
    # gain: a flat field comes back flat, (A g)(c(p)) = 1
    seen = (target.abs() < limit).all(-1)  # display pixels seen inside the frame
    gain = torch.ones(3, h, w, dtype=dtype)
    with torch.no_grad():
        for _ in range(gain_iterations + 1):
            eye = op(gain[None])[0]  # [3, H, W]
            at = F.grid_sample(eye[:, None], target, mode="bilinear", padding_mode="border", align_corners=False)[:, 0]
            update = torch.where(seen, 1.0 / at.clamp(min=1e-6), torch.ones_like(at)).clamp(0.5, 2.0)
            residual = float((at - 1.0)[seen].abs().max())  # seen in every channel: it holds the valid pixels
            if _ == gain_iterations:
                break
            gain = _fill_invalid((gain * update)[..., None], seen)[..., 0]
    residuals = {"flat_max_abs": residual, "measured_fraction": float(valid.double().mean())}
    return (target - p).float(), gain.float(), residuals


def fit_bank_prewarp(
    optics: "torch.nn.Module | PSFBank | None" = None,
    size: int | Sequence[int] = FIT_SIZES,
    *,
    modes: Sequence[str] = ("distortion", "exact"),
    gain_iterations: int = 4,
    pool: int = 2,
    dtype: torch.dtype = torch.float64,
) -> DisplayLUTMap:
    """Fit the default pre-warp (map + gain per primary, see the module docstring) for an optics.

    Args:
        optics: an optics stage (its bank and options, e.g. radiometry, are used; its mode is
            replaced by each of ``modes``), a :class:`PSFBank` (default optics options) or None (the
            shipped Cardboard bank).
        size: display pixels along the display's shorter side (the tables' resolution; the fit is
            exact for the operator at this pixel pitch), or several: one table per size and mode,
            an image is served by those of the two sizes whose pitch brackets its own (the
            operators place light at their pixel pitch, which moves a dot's centroid by up to
            ~0.1 px between 96 and 256 px; :class:`~.bank_maps.DisplayLUTMap`). Default
            :data:`FIT_SIZES`.
        modes: optics modes to fit a table for (``"fast"`` uses the ``"exact"`` table).
        gain_iterations: fixed-point iterations of the gain (0: the lens's own fall-off, unit gain).
        pool: the tables are stored at ``size / pool`` (``pool x pool`` averages: the fitted tables
            resampled bilinearly at the coarser pixel centres).
        dtype: working precision.
    Returns:
        A :class:`DisplayLUTMap` over the whole display (``meta`` holds the bank's fingerprint,
        the settings and the residuals); ``.save(path)`` writes it.
    Raises:
        InputValueError: a bad argument (named), or an optics through which some primary has no
            display pixel to measure (its light leaves the eye frame everywhere: nothing to fit).
    """
    from .optics.bank import PSFBank
    from .optics.stage import PSFOptics

    if optics is None or isinstance(optics, PSFBank):
        optics = PSFOptics(optics)
    if not hasattr(optics, "mode"):
        raise InputValueError(f"optics must be an optics stage or a PSFBank, got {type(optics).__name__}")
    bank, placement = _optics_bank(optics), _optics_placement(optics)
    sizes = [size] if isinstance(size, int) else list(size) if isinstance(size, Sequence) else [size]
    if not sizes or any(isinstance(n, bool) or not isinstance(n, int) or n < 8 for n in sizes) or len(set(sizes)) < len(sizes):
        raise InputValueError(f"size must be an int >= 8 or a sequence of different ones, got {size!r}")
    if not isinstance(pool, int) or pool < 1 or any(n % pool or n // pool < 4 for n in sizes):
        raise InputValueError(f"pool must be an int >= 1 dividing size into >= 4 samples (size {size!r}), got {pool!r}")
    if isinstance(gain_iterations, bool) or not isinstance(gain_iterations, int) or gain_iterations < 0:
        raise InputValueError(f"gain_iterations must be an int >= 0, got {gain_iterations!r}")
    if not modes or any(m not in ("distortion", "exact", "fast") for m in modes):
        raise InputValueError(f"modes must be a non-empty subset of ('distortion', 'exact', 'fast'), got {modes!r}")
    dw, dh = bank.display_mm
    main = max(sizes)

    def fit_size(n: int) -> tuple[int, int]:
        long = pool * max(1, round(n * max(dw, dh) / min(dw, dh) / pool))
        return (n, long) if dw >= dh else (long, n)

    tables: dict[int, dict[str, tuple[torch.Tensor, torch.Tensor]]] = {n: {} for n in sizes}
    residuals: dict[int, dict[str, dict[str, float]]] = {n: {} for n in sizes}
    start = time.perf_counter()
    for m in modes:
        stage = copy.copy(optics)  # the caller's options, with the display spanned by the fit image
        # nn.Module's stubs type every attribute as a tensor or module; mode and placement are plain ones
        stage.mode, stage.placement = m, "stretch"  # type: ignore[assignment]
        for n in sizes:
            disp, gain, res = _fit_mode(stage, bank, fit_size(n), gain_iterations, dtype)
            disp = F.avg_pool2d(disp.permute(0, 3, 1, 2), pool).permute(0, 2, 3, 1)
            tables[n][m], residuals[n][m] = (disp, F.avg_pool2d(gain[:, None], pool)[:, 0]), res
    meta = {"bank": bank_fingerprint(bank), "radiometry": getattr(optics, "radiometry", None), "size": list(fit_size(main)),
            "pool": pool, "gain_iterations": gain_iterations, "optics": repr(optics), "residuals": residuals[main],
            "seconds": round(time.perf_counter() - start, 2)}
    if len(sizes) > 1:
        meta.update(sizes=sorted(sizes), residuals_by_size={str(n): residuals[n] for n in sorted(sizes)})
    more = {m: {n: tables[n][m] for n in sizes if n != main} for m in modes} if len(sizes) > 1 else None
    return DisplayLUTMap(tables[main], bank.display_mm, placement, meta=meta, size=main, sizes=more)
