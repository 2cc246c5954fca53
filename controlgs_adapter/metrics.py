"""Image-quality metrics: PSNR and SSIM in plain torch (differentiable), LDR-FLIP through NVIDIA's
``flip-evaluator`` (a dependency), and the report's per-image metric set.

SSIM follows Wang et al. 2004 as 3DGS and pytorch-msssim use it: an 11-tap Gaussian window with
sigma 1.5 (separable, normalised), constants ``C1 = (0.01 L)^2``, ``C2 = (0.03 L)^2``, population
(co)variances, per-channel maps averaged over the valid window positions (no padding) and the
channels. ``data_range`` L is always explicit. LPIPS (local weights only) is in
:mod:`controlgs_adapter.perceptual`. ColorVideoVDP (``cvvdp``, installed with ``--no-deps`` by
``scripts/setup.sh``; :mod:`controlgs_adapter.cvvdp_shim`) scores a display of a given pixels per degree.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Union

import torch
import torch.nn.functional as F

from .checks import check_image
from .cvvdp_shim import import_pycvvdp
from .errors import InputValueError, MissingDependencyError, ShapeError

__all__ = ["psnr", "ssim", "ssim_map", "flip", "FLIP_PPD", "gaussian_window", "check_image_pair", "optional_metrics", "ColorVideoVDP",
           "CVVDP_DISPLAY", "cvvdp_missing"]

#: FLIP's default observer: pixels per degree of a 0.7 m wide 4K display seen from 0.7 m
FLIP_PPD = 0.7 * (3840 / 0.7) * math.pi / 180.0


def check_image_pair(x: torch.Tensor, y: torch.Tensor, names: tuple[str, str] = ("x", "y")) -> None:
    """Two images ``[..., 3, H, W]`` of one shape; errors name them ``names``."""
    check_image(names[0], x)
    check_image(names[1], y)
    if x.shape != y.shape:
        raise ShapeError(f"{names[0]} and {names[1]} must have the same shape, got {list(x.shape)} and {list(y.shape)}")


def psnr(x: torch.Tensor, y: torch.Tensor, *, data_range: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB of each image: ``x, y`` ``[..., 3, H, W]`` -> ``[...]``
    (``+inf`` for identical images)."""
    check_image_pair(x, y)
    mse = (x - y).square().mean(dim=(-3, -2, -1))
    return 10.0 * torch.log10(data_range**2 / mse)


def gaussian_window(size: int = 11, sigma: float = 1.5, *, dtype: torch.dtype = torch.float32,
                    device: torch.device | str | None = None) -> torch.Tensor:
    """Normalised 1-D Gaussian ``[size]`` sampled at integer offsets about the centre."""
    if size < 1 or size % 2 == 0:
        raise InputValueError(f"window size must be odd and >= 1, got {size!r}")
    r = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(r**2) / (2.0 * sigma**2))
    return g / g.sum()


def ssim(x: torch.Tensor, y: torch.Tensor, *, data_range: float = 1.0, window_size: int = 11,
         sigma: float = 1.5) -> torch.Tensor:
    """Structural similarity of each image: ``x, y`` ``[..., 3, H, W]`` -> ``[...]``, the mean of :func:`ssim_map`.

    Needs ``H, W >= window_size`` (valid window positions only)."""
    return ssim_map(x, y, data_range=data_range, window_size=window_size, sigma=sigma).mean(dim=(-3, -2, -1))


def ssim_map(x: torch.Tensor, y: torch.Tensor, *, data_range: float = 1.0, window_size: int = 11,
             sigma: float = 1.5) -> torch.Tensor:
    """Per-window SSIM ``[..., 3, H - window_size + 1, W - window_size + 1]`` of ``x, y`` ``[..., 3, H, W]``: entry
    ``(i, j)`` is the window centred on pixel ``(i + window_size // 2, j + window_size // 2)``."""
    check_image_pair(x, y)
    h, w = x.shape[-2:]
    if h < window_size or w < window_size:
        raise ShapeError(f"ssim needs images of at least {window_size}x{window_size} pixels (window size), got {h}x{w}")
    lead, c = x.shape[:-3], x.shape[-3]
    g = gaussian_window(window_size, sigma, dtype=x.dtype, device=x.device)
    gh = g.view(1, 1, 1, -1).expand(c, 1, 1, window_size)
    gv = g.view(1, 1, -1, 1).expand(c, 1, window_size, 1)

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(t, gh, groups=c), gv, groups=c)

    xs = x.reshape(-1, c, h, w)
    ys = y.reshape(-1, c, h, w)
    mu_x, mu_y = blur(xs), blur(ys)
    sxx = blur(xs * xs) - mu_x**2
    syy = blur(ys * ys) - mu_y**2
    sxy = blur(xs * ys) - mu_x * mu_y
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    smap = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return smap.reshape(*lead, *smap.shape[-3:])


def flip(test: torch.Tensor, reference: torch.Tensor, *, ppd: float = FLIP_PPD) -> float:
    """Mean LDR-FLIP error of ``test`` against ``reference`` (NVIDIA's ``flip-evaluator``; lower is
    better, 0 for identical images): one sRGB image pair ``[3, H, W]`` with values in [0, 1], passed
    to the package as the ``H x W x 3`` float64 sRGB arrays it expects. Not differentiable. Every
    refusal names the argument at fault, ``test`` or ``reference``."""
    check_image_pair(test, reference, ("test", "reference"))
    if test.dim() != 3:
        raise ShapeError(f"flip takes one image pair [3, H, W], got {list(test.shape)}")
    # the package calls sys.exit() on bad arguments: check them here
    if isinstance(ppd, bool) or not isinstance(ppd, (int, float)) or not math.isfinite(ppd) or ppd <= 0:
        raise InputValueError(f"flip: ppd must be a finite number > 0 (pixels per degree), got {ppd!r}")
    for name, img in (("test", test), ("reference", reference)):
        lo, hi = float(img.detach().min()), float(img.detach().max())
        if lo < 0.0 or hi > 1.0:
            raise InputValueError(f"flip: {name} must hold sRGB values in [0, 1] (LDR-FLIP), got [{lo:.4g}, {hi:.4g}]")
    try:
        import flip_evaluator  # type: ignore[import-not-found]
    except ImportError:
        raise InputValueError("FLIP needs the flip-evaluator package (a dependency of controlgs-adapter): "
                              "pip install flip-evaluator") from None

    def hwc(img: torch.Tensor) -> Any:
        return img.detach().permute(1, 2, 0).to("cpu", torch.float64).contiguous().numpy()

    return float(flip_evaluator.evaluate(hwc(reference), hwc(test), "LDR", applyMagma=False,
                                         parameters={"ppd": float(ppd)})[1])


#: the ColorVideoVDP display model whose photometry (sRGB, 200 cd/m2 peak) every score uses; its geometry is replaced
CVVDP_DISPLAY = "standard_4k"
#: pixels per degree: a number, or a function ``(height, width) -> ppd`` of the image size
PPD = Union[float, Callable[[int, int], float]]


class ColorVideoVDP:
    """ColorVideoVDP (``pycvvdp.cvvdp``, MIT): the JOD of one sRGB image pair ``[3, H, W]`` in [0, 1] (values
    outside are clamped; higher is better, 10 for identical images; not differentiable here), on a ``W x H``
    display seen at ``ppd`` pixels per degree (``pycvvdp.vvdp_display_geometry((W, H), ppd=...)``) with the
    photometry of :data:`CVVDP_DISPLAY`. Runs on the images' device.

    ``ppd``: a number or a function of the image size ``(H, W)``. ``ppd_used``: ``{"WxH": ppd}`` of every
    size scored so far. Raises :class:`MissingDependencyError` when ``cvvdp`` does not import."""

    def __init__(self, ppd: PPD) -> None:
        self._pycvvdp = import_pycvvdp()
        self._ppd = ppd
        self._metrics: dict[tuple[str, str], Any] = {}
        self.ppd_used: dict[str, float] = {}

    def metric(self, height: int, width: int, device: torch.device | str = "cpu") -> Any:
        """The ``pycvvdp.cvvdp`` metric for ``height x width`` images on ``device`` (made once)."""
        size = f"{width}x{height}"
        if size not in self.ppd_used:
            ppd = self._ppd(height, width) if callable(self._ppd) else self._ppd
            if isinstance(ppd, bool) or not isinstance(ppd, (int, float)) or not math.isfinite(ppd) or ppd <= 0:
                raise InputValueError(f"cvvdp: ppd must be a finite number > 0 (pixels per degree), got {ppd!r} for {size}")
            self.ppd_used[size] = float(ppd)
        key = (size, str(device))
        if key not in self._metrics:
            geometry = self._pycvvdp.vvdp_display_geometry((width, height), ppd=self.ppd_used[size])
            self._metrics[key] = self._pycvvdp.cvvdp(display_name=CVVDP_DISPLAY, display_geometry=geometry,
                                                     device=torch.device(device), quiet=True)
        return self._metrics[key]

    def __call__(self, test: torch.Tensor, reference: torch.Tensor) -> float:
        check_image_pair(test, reference, ("test", "reference"))
        if test.dim() != 3:
            raise ShapeError(f"cvvdp takes one image pair [3, H, W], got {list(test.shape)}")
        metric = self.metric(test.shape[-2], test.shape[-1], test.device)

        def hwc(img: torch.Tensor) -> torch.Tensor:
            return img.detach().clamp(0, 1).permute(1, 2, 0).float()

        jod, _ = metric.predict(hwc(test), hwc(reference), dim_order="HWC")
        return float(jod)


def cvvdp_missing() -> str | None:
    """Why ColorVideoVDP cannot run here (one line), or None when it imports."""
    try:
        import_pycvvdp()
    except MissingDependencyError as e:
        return str(e)
    return None


def optional_metrics(lpips: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None, *,
                     ppd: PPD | None = None) -> dict[str, Callable[[torch.Tensor, torch.Tensor], float]]:
    """The report's metrics beyond PSNR and SSIM, as ``{name: f(eye, gt) -> float}`` on one sRGB
    image pair ``[3, H, W]`` in [0, 1]: ``"flip"`` (LDR-FLIP, lower is better; always),
    ``"lpips"`` (lower is better) when an LPIPS network is given (:func:`~controlgs_adapter.perceptual.load_lpips`),
    and ``"cvvdp"`` (a :class:`ColorVideoVDP` at ``ppd`` pixels per degree, higher is better) when ``ppd`` is
    given and ``cvvdp`` imports (:func:`cvvdp_missing` says why not). Nothing is ever downloaded."""
    found: dict[str, Callable[[torch.Tensor, torch.Tensor], float]] = {"flip": flip}
    if lpips is not None:
        def lpips_metric(eye: torch.Tensor, gt: torch.Tensor) -> float:
            return float(lpips(eye, gt))

        found["lpips"] = lpips_metric
    if ppd is not None and cvvdp_missing() is None:
        found["cvvdp"] = ColorVideoVDP(ppd)
    return found
