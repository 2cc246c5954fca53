"""Backend for Scaffold-GS (city-super/Scaffold-GS) and models laid out like it.

Scaffold-GS's ``GaussianModel`` is a plain Python object (not an ``nn.Module``) holding the
decoders ``mlp_opacity``, ``mlp_cov``, ``mlp_color`` (``nn.Sequential`` whose child 0 is
``Linear(feat_dim + 3 (+1) (+appearance_dim), feat_dim)``), an optional ``mlp_feature_bank``
(not a target: it re-weights the feature before the decoders) and the anchors ``_anchor [A, 3]``
(``get_anchor``). A loaded checkpoint holds the decoders as TorchScript traces; they are rebuilt
as eager modules when wrapped (:meth:`Backend.make_hookable`).

Row mapping: Scaffold-GS's renderer slices every decoder input with the boolean visibility mask,
so row i belongs to anchor ``visible_mask.nonzero()[i]`` (:meth:`visible_rows_to_anchor_ids`).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from controlgs_adapter.backend import Backend, anchor_ids_from_mask, get_attr_path
from controlgs_adapter.checks import check_tensor

from controlgs_adapter.formats.decoders import ATTRIBUTE_DECODERS

__all__ = ["ScaffoldGSBackend"]


FEATURE_BANK = "mlp_feature_bank"


def _is_decoder(obj: Any) -> bool:
    return isinstance(obj, (nn.Module, torch.jit.ScriptModule))


class ScaffoldGSBackend(Backend):
    """Scaffold-GS layout: any object with decoder modules ``mlp_opacity``, ``mlp_cov``,
    ``mlp_color`` and anchors ``get_anchor`` or ``_anchor``.

    Matching is duck-typed. It is the most generic backend, so the built-in list tries it last
    (Octree-GS, HAC, ... share these attribute names).
    """

    name = "scaffold_gs"

    def matches(self, model: Any) -> bool:
        has_decoders = all(_is_decoder(getattr(model, d, None)) for d in ATTRIBUTE_DECODERS)
        return has_decoders and (hasattr(model, "get_anchor") or hasattr(model, "_anchor"))

    def decoder_paths(self, model: Any) -> list[str]:
        extra = [FEATURE_BANK] if _is_decoder(getattr(model, FEATURE_BANK, None)) else []
        return [*ATTRIBUTE_DECODERS, *extra]

    def default_targets(self, model: Any) -> list[str]:
        return list(ATTRIBUTE_DECODERS)

    def input_layout(self, model: Any, decoder_path: str) -> list[tuple[str, int]] | None:
        """``[feat F, view 3, (dist 1), (appearance A, colour only)]`` from the model's configuration
        attributes (``feat_dim``, ``add_<x>_dist``, ``appearance_dim``); None for the feature bank or a
        model without ``feat_dim``.

        A model without the ``add_<x>_dist`` attribute (laid out like Scaffold-GS but not its class)
        gets the distance input inferred from the width of the decoder's first layer: present when it
        takes exactly one input more than the layout without it (eager and TorchScript decoders alike).
        """
        if decoder_path not in ATTRIBUTE_DECODERS or not hasattr(model, "feat_dim"):
            return None
        extra = self.extra_inputs(model)
        app = int(getattr(model, "appearance_dim", 0) or 0)
        tail = [("appearance", app)] if decoder_path == "mlp_color" and app > 0 else []
        base = [("feat", int(model.feat_dim)), ("view", 3)]
        flag = f"add_{decoder_path.removeprefix('mlp_')}_dist"
        if hasattr(model, flag):
            dist = bool(getattr(model, flag))
        else:
            dist = self._first_width(model, decoder_path) == sum(w for _, w in base + extra + tail) + 1
        return base + ([("dist", 1)] if dist else []) + extra + tail

    def _first_width(self, model: Any, decoder_path: str) -> int | None:
        """Input width of the decoder's first layer (eager or TorchScript), None if it has none."""
        try:
            weight = get_attr_path(model, self.first_linear_path(model, decoder_path)).weight
        except (AttributeError, IndexError, KeyError, TypeError):
            return None
        return int(weight.shape[1]) if isinstance(weight, torch.Tensor) and weight.dim() == 2 else None

    def extra_inputs(self, model: Any) -> list[tuple[str, int]]:
        """Inputs a variant adds after ``[feat, view, (dist)]`` (Octree-GS: the level)."""
        return []

    def anchor_positions(self, model: Any) -> torch.Tensor:
        anchors = getattr(model, "get_anchor", None)
        if anchors is None:
            anchors = model._anchor
        elif callable(anchors) and not isinstance(anchors, torch.Tensor):
            anchors = anchors()
        check_tensor("model.get_anchor", anchors, ["A", 3])
        return anchors

    @staticmethod
    def visible_rows_to_anchor_ids(visible_mask: torch.Tensor) -> torch.Tensor:
        """``[A]`` bool visibility mask -> ``[R]`` long ids (row i = i-th visible anchor, ascending),
        exactly the order in which Scaffold-GS's renderer feeds the decoders."""
        return anchor_ids_from_mask(visible_mask)
