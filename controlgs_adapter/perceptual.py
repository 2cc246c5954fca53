"""LPIPS (Zhang et al. 2018, v0.1, AlexNet trunk) in plain torch, from weights the user has on disk.

No package ships the AlexNet backbone weights and nothing is ever downloaded, so
:func:`load_lpips` takes local files: the backbone (torchvision's ``alexnet-owt-7be5be79.pth``,
keys ``features.{0,3,6,8,10}.{weight,bias}``) and the linear head (the ``lpips`` package's
``weights/v0.1/alex.pth``, keys ``lin{0..4}.model.1.weight``), or one file holding both (a saved
``lpips.LPIPS(net="alex").state_dict()``: ``net.slice{1..5}.*`` + ``lin*``). When only the
backbone is given and the ``lpips`` package is installed (``pip install --no-deps lpips``), its
head file is used. Files load with ``torch.load(weights_only=True)`` or as safetensors; anything
else is refused.

The network: inputs in [0, 1] are mapped to [-1, 1], shifted and scaled per channel, passed
through AlexNet's five conv + ReLU layers (max-pooling before the 2nd and 3rd); each ReLU output is
unit-normalised over channels, the squared difference weighted by the head's 1x1 conv, averaged
over the image and summed over the five layers.
"""

from __future__ import annotations

import importlib.util
import pickle
from pathlib import Path
from typing import Sequence

import torch
import torch.nn.functional as F

from .errors import InputValueError, ShapeError
from .metrics import check_image_pair

__all__ = ["LPIPS", "load_lpips", "LPIPS_MIN_SIZE"]

#: AlexNet's conv layers: (index in ``features``, out channels, in channels, kernel, stride, padding)
_CONVS = ((0, 64, 3, 11, 4, 2), (3, 192, 64, 5, 1, 2), (6, 384, 192, 3, 1, 1), (8, 256, 384, 3, 1, 1),
          (10, 256, 256, 3, 1, 1))
_SHIFT = (-0.030, -0.088, -0.188)
_SCALE = (0.458, 0.448, 0.450)
#: smallest image side the five AlexNet layers take (11x11 stride 4, two 3x3 stride-2 pools)
LPIPS_MIN_SIZE = 31


def _canonical(key: str) -> str | None:
    """Our name (``conv{i}.weight|bias``, ``lin{i}``) of a torchvision / lpips key, None if unused."""
    parts = key.split(".")
    index = {c[0]: i for i, c in enumerate(_CONVS)}
    if len(parts) == 3 and parts[0] == "features" and parts[1].isdigit() and parts[2] in ("weight", "bias"):
        i = index.get(int(parts[1]))
        return None if i is None else f"conv{i}.{parts[2]}"
    if (len(parts) == 4 and parts[0] == "net" and parts[1].startswith("slice") and parts[2].isdigit()
            and parts[3] in ("weight", "bias")):
        i = index.get(int(parts[2]))
        return None if i is None else f"conv{i}.{parts[3]}"
    if len(parts) == 4 and parts[0][:3] == "lin" and parts[1] == "model" and parts[2] in ("0", "1") and parts[3] == "weight":
        return parts[0] if parts[0][3:] in ("0", "1", "2", "3", "4") else None
    return None


def _expected() -> dict[str, tuple[int, ...]]:
    shapes: dict[str, tuple[int, ...]] = {}
    for i, (_, out, inp, k, _, _) in enumerate(_CONVS):
        shapes[f"conv{i}.weight"] = (out, inp, k, k)
        shapes[f"conv{i}.bias"] = (out,)
        shapes[f"lin{i}"] = (1, out, 1, 1)
    return shapes


def _read(path: Path) -> dict[str, torch.Tensor]:
    """A flat ``{key: tensor}`` file: safetensors, or a tensor-only torch checkpoint."""
    if not path.is_file():
        raise InputValueError(f"LPIPS weights {path}: no such file")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            data = load_file(str(path))  # on the CPU
        else:
            data = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        raise InputValueError(f"LPIPS weights {path}: refused, not a tensor-only checkpoint (loaded with "
                              f"torch.load(weights_only=True), which never runs code): {str(e).splitlines()[0]}") from None
    except Exception as e:  # noqa: BLE001 - a foreign file fails in many ways; each is one message
        raise InputValueError(f"LPIPS weights {path}: not a torch checkpoint or safetensors file "
                              f"({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''})") from None
    if not isinstance(data, dict) or not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in data.items()):
        raise InputValueError(f"LPIPS weights {path}: expected a flat {{name: tensor}} state dict, got {type(data).__name__}")
    return data


def _lpips_package_head() -> Path | None:
    """The ``lpips`` package's AlexNet head file, found without importing it (it imports torchvision)."""
    spec = importlib.util.find_spec("lpips")
    if spec is None or not spec.submodule_search_locations:
        return None
    path = Path(list(spec.submodule_search_locations)[0]) / "weights" / "v0.1" / "alex.pth"
    return path if path.is_file() else None


class LPIPS(torch.nn.Module):
    """LPIPS v0.1 with the AlexNet trunk: ``lpips(x, y)`` on sRGB images ``[..., 3, H, W]`` in
    [0, 1] (H, W >= :data:`LPIPS_MIN_SIZE`) -> ``[...]`` distances (0 for identical images,
    symmetric). Frozen; build it with :func:`load_lpips`. ``source`` names the weight files."""

    shift: torch.Tensor  # [3, 1, 1] buffers: LPIPS input normalisation
    scale: torch.Tensor

    def __init__(self, weights: dict[str, torch.Tensor], source: str = "") -> None:
        super().__init__()
        expected = _expected()
        missing = sorted(set(expected) - set(weights))
        if missing:
            hint = {"conv": " (the AlexNet backbone: torchvision's alexnet-owt-7be5be79.pth)",
                    "lin": " (the LPIPS head: the lpips package's weights/v0.1/alex.pth; pip install --no-deps lpips)"}
            raise InputValueError(f"LPIPS weights {source}: missing {missing}"
                                  + "".join(h for k, h in hint.items() if any(m.startswith(k) for m in missing)))
        for name, shape in expected.items():
            w = weights[name]
            if tuple(w.shape) != shape or not w.is_floating_point():
                raise InputValueError(f"LPIPS weights {source}: {name} must be a float tensor of shape {list(shape)}, "
                                      f"got {w.dtype} {list(w.shape)}")
            self.register_buffer(name.replace(".", "_"), w.detach().to(torch.float32).clone())
        self.register_buffer("shift", torch.tensor(_SHIFT).view(3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(3, 1, 1))
        self.source = source
        self.eval()

    def features(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The five ReLU outputs of AlexNet for ``x`` ``[B, 3, H, W]`` (already scaled)."""
        taps = []
        for i, (_, _, _, _, stride, pad) in enumerate(_CONVS):
            if i in (1, 2):
                x = F.max_pool2d(x, 3, 2)
            x = F.relu(F.conv2d(x, getattr(self, f"conv{i}_weight"), getattr(self, f"conv{i}_bias"), stride, pad))
            taps.append(x)
        return taps

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        check_image_pair(x, y)
        h, w = x.shape[-2:]
        if min(h, w) < LPIPS_MIN_SIZE:
            raise ShapeError(f"LPIPS (AlexNet) needs images of at least {LPIPS_MIN_SIZE}x{LPIPS_MIN_SIZE} pixels, got {h}x{w}")
        lead = x.shape[:-3]
        dtype = self.shift.dtype
        both = torch.cat([x.reshape(-1, 3, h, w), y.reshape(-1, 3, h, w)]).to(dtype)
        feats = self.features(((2.0 * both - 1.0) - self.shift) / self.scale)
        n = both.shape[0] // 2
        total = torch.zeros(n, dtype=dtype, device=both.device)
        for i, f in enumerate(feats):
            f = f / (f.square().sum(dim=1, keepdim=True).sqrt() + 1e-10)
            total = total + F.conv2d((f[:n] - f[n:]).square(), getattr(self, f"lin{i}")).mean(dim=(-3, -2, -1))
        return total.reshape(lead)


def load_lpips(paths: str | Path | Sequence[str | Path]) -> LPIPS:
    """LPIPS(alex) from local weight files (see the module doc): their tensors are merged; keys other
    than AlexNet / LPIPS-head names (e.g. torchvision's ``classifier.*``) are ignored. A file whose keys
    give neither the backbone nor the head, or a missing or mis-shaped tensor, is refused naming the
    file(s) and the keys."""
    files = [Path(paths)] if isinstance(paths, (str, Path)) else [Path(p) for p in paths]
    if not files:
        raise InputValueError("LPIPS: no weight files given")
    weights: dict[str, torch.Tensor] = {}
    for path in files:
        data = _read(path)
        mapped = {c: v for k, v in data.items() if (c := _canonical(k)) is not None}
        if not mapped:
            raise InputValueError(f"LPIPS weights {path}: none of its keys is an AlexNet backbone key "
                                  f"(features.N.weight, net.sliceK.N.weight) or an LPIPS head key (linK.model.1.weight); "
                                  f"it holds {sorted(data)[:8]}{' ...' if len(data) > 8 else ''}")
        weights.update(mapped)
    source = ", ".join(str(p) for p in files)
    if not any(k.startswith("lin") for k in weights):
        head = _lpips_package_head()
        if head is not None:
            weights.update({c: v for k, v in _read(head).items() if (c := _canonical(k)) is not None})
            source += f" + {head}"
    return LPIPS(weights, source)
