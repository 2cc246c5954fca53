"""The backend interface: how to recognise and adapt one neural-Gaussian model family.

A backend never imports the family's code: it duck-types the model on its real attribute names.
Built-in backends live in ``controlgs_adapter.backends`` and register through
``controlgs_register_backends`` exactly like third-party ones.
"""

from __future__ import annotations

import hashlib
import re
from typing import Any, ClassVar, Sequence

import torch
from torch import nn

from .checks import check_tensor
from .errors import TargetError
from .formats.torchscript_live import eager_from_script
from .rendering.renderer import Renderer, default_renderer

__all__ = ["Backend", "get_attr_path", "set_attr_path", "has_attrs", "anchor_ids_from_mask"]


def get_attr_path(obj: Any, path: str) -> Any:
    """``get_attr_path(model, "network.prediction_net.0")``; integer parts index sequences."""
    for part in path.split("."):
        obj = obj[int(part)] if part.isdigit() and not hasattr(obj, part) else getattr(obj, part)
    return obj


def has_attrs(obj: object, names: Sequence[str]) -> bool:
    """True if every dotted name resolves on ``obj`` (values may be None)."""
    for name in names:
        cur = obj
        for part in name.split("."):
            if not hasattr(cur, part):
                return False
            cur = getattr(cur, part)
    return True


def set_attr_path(obj: Any, path: str, value: Any) -> None:
    """Set the attribute (or sequence item) at a dotted ``path``."""
    head, _, last = path.rpartition(".")
    parent = get_attr_path(obj, head) if head else obj
    if last.isdigit() and not hasattr(parent, last):
        parent[int(last)] = value
    else:
        setattr(parent, last, value)


def anchor_ids_from_mask(mask: torch.Tensor, num_anchors: int | None = None, *, name: str = "visible_mask") -> torch.Tensor:
    """``[A]`` bool mask -> ``[R]`` ascending anchor ids: the order boolean indexing gives, i.e.
    row ``i`` of a decoder input sliced with ``mask`` is anchor ``ids[i]``."""
    check_tensor(name, mask, ["A"] if num_anchors is None else [num_anchors], dtypes=(torch.bool,))
    return mask.nonzero().squeeze(1)


class Backend:
    """Base class of backend plug-ins. Subclasses set :attr:`name` and implement :meth:`matches`,
    :meth:`decoder_paths` and :meth:`anchor_positions`; the rest has defaults that fit the
    Scaffold-GS layout.

    Vocabulary: a *decoder* is a module whose first ``nn.Linear`` (``FC1``) gets the injection; a
    *row* is one row of the decoder input; :meth:`rows_per_anchor` rows belong to each anchor
    (row ``r`` is anchor ``anchor_ids[r // rows_per_anchor]``).
    """

    name: ClassVar[str] = ""

    def matches(self, model: Any) -> bool:
        """True if this backend knows the model (duck-typed on attribute names)."""
        raise NotImplementedError

    def decoder_paths(self, model: Any) -> list[str]:
        """Dotted attribute paths of all decoders that may be targeted, e.g. ``["mlp_opacity", ...]``."""
        raise NotImplementedError

    def default_targets(self, model: Any) -> list[str]:
        """Decoders targeted when ``ControlGS.wrap(targets=None)``: by default all of them."""
        return self.decoder_paths(model)

    def first_linear_path(self, model: Any, decoder_path: str) -> str:
        """Dotted path of the decoder's first Linear (FC1). Default: child ``0`` of a Sequential."""
        return f"{decoder_path}.0"

    def anchor_positions(self, model: Any) -> torch.Tensor:
        """``[A, 3]`` anchor positions exactly as the decoder sees them (world units)."""
        raise NotImplementedError

    def num_anchors(self, model: Any) -> int:
        """Number of anchors A (rows of the condition table)."""
        return int(self.anchor_positions(model).shape[0])

    def rows_per_anchor(self, model: Any) -> int:
        """How many consecutive decoder rows belong to one anchor (CompGS: K; Scaffold-GS: 1)."""
        return 1

    def rows_for(self, model: Any, mask: torch.Tensor) -> torch.Tensor:
        """A view's ``[A]`` bool visibility mask (what the family's prefilter returns) -> ``[R]``
        ascending ids of the anchors whose rows the decoders get: rows ``i * K .. i * K + K - 1``
        (K = :meth:`rows_per_anchor`) belong to anchor ``ids[i]``. Default: ``mask.nonzero()``."""
        return anchor_ids_from_mask(mask, self.num_anchors(model))

    def input_layout(self, model: Any, decoder_path: str) -> list[tuple[str, int]] | None:
        """The inputs of a decoder's FC1 in order, ``[(name, width)]`` (e.g. ``[("feat", 32),
        ("view", 3)]``), or None where the backend does not know them. :meth:`check_decoder`
        checks FC1's width against it."""
        return None

    def make_hookable(self, model: Any, decoder_path: str) -> nn.Module | None:
        """Make a decoder take hooks (e.g. rebuild a TorchScript decoder as an eager module with
        identical outputs) and install it on the model. Return the original module (to restore on
        unwrap) or None if nothing changed. Called only after every check passed."""
        module = get_attr_path(model, decoder_path)
        if isinstance(module, torch.jit.ScriptModule):
            set_attr_path(model, decoder_path, eager_from_script(module, name=decoder_path))
            return module
        return None

    def check_decoder(self, model: Any, decoder_path: str,
                      rebuilt: nn.Module | None = None) -> nn.Linear | torch.jit.ScriptModule:
        """Return FC1 of a decoder, or raise :class:`TargetError` saying what is wrong (no first
        Linear, or a width that differs from :meth:`input_layout`'s). ``rebuilt``: the eager rebuild
        of a TorchScript decoder; FC1 is then taken from it, at the same path inside the decoder, and
        checked the same way."""
        fc1_path = self.first_linear_path(model, decoder_path)
        try:
            if rebuilt is None:
                fc1 = get_attr_path(model, fc1_path)
            elif fc1_path.startswith(decoder_path + "."):
                fc1 = get_attr_path(rebuilt, fc1_path[len(decoder_path) + 1:])
            else:
                raise TargetError(f"{self.name}: FC1 path {fc1_path!r} of TorchScript decoder {decoder_path!r} is not inside it")
        except (AttributeError, IndexError, KeyError, TypeError) as e:
            raise TargetError(f"{self.name}: decoder {decoder_path!r} has no first layer {fc1_path!r}: {e}") from e
        ok = isinstance(fc1, nn.Linear) or (
            isinstance(fc1, torch.jit.ScriptModule) and getattr(fc1, "original_name", "") == "Linear"
        )
        if not ok:
            raise TargetError(f"{self.name}: first layer of {decoder_path!r} must be a Linear, got {type(fc1).__name__}")
        layout = self.input_layout(model, decoder_path)
        if layout is not None and fc1.weight.shape[1] != sum(w for _, w in layout):
            where = re.sub(r"\.(\d+)$", r"[\1]", fc1_path)
            raise TargetError(f"{self.name}: {where} takes {fc1.weight.shape[1]} inputs, the model's configuration gives "
                              f"{sum(w for _, w in layout)} ({layout})")
        return fc1

    def renderer(self, model: Any) -> Renderer | None:
        """The :class:`~controlgs_adapter.rendering.renderer.Renderer` of this family for ``model``, or None
        when the model cannot render itself (the user passes one). Default:
        :func:`~controlgs_adapter.rendering.renderer.default_renderer` (a
        :class:`~controlgs_adapter.rendering.renderer.ModelRenderer` when the model has ``visible_anchors``
        and ``render``: every family the library loads)."""
        return default_renderer(model)

    def fingerprint(self, model: Any, anchor_ids: torch.Tensor | None = None) -> str:
        """SHA-256 (hex, 16 chars) over anchor positions and every decoder's weights: identifies the
        backbone an adapter was trained on. ``anchor_ids`` (``LongTensor[R]``): hash only those
        anchors' positions, in that order (None: all)."""
        h = hashlib.sha256()
        pos = self.anchor_positions(model).detach()
        if anchor_ids is not None:
            pos = pos.index_select(0, anchor_ids.to(pos.device))
        pos = pos.to("cpu", torch.float32).contiguous()
        h.update(str(tuple(pos.shape)).encode())
        h.update(pos.numpy().tobytes())
        for path in self.decoder_paths(model):
            for k, v in sorted(get_attr_path(model, path).state_dict().items()):
                h.update(f"{path}.{k}{tuple(v.shape)}".encode())
                h.update(v.detach().to("cpu", torch.float32).contiguous().numpy().tobytes())
        return h.hexdigest()[:16]
