"""The paper's ablations (Tbl. 4): which condition modules each trains and whether it is state-blind.

Shared by training (``controlgs train`` / ``demo``), evaluation, the viewer and the report.
"""

from __future__ import annotations

from typing import Iterable

__all__ = ["ABLATIONS", "ABLATION_EFFECT", "ablations_for"]

#: ablation name -> (modules trained, state_blind), paper Tbl. 4; ``wo_foveation``: the paper's three modules,
#: without the foveation condition
ABLATIONS: dict[str, tuple[tuple[str, ...], bool]] = {
    "wo_lens": (("resample", "display"), False),
    "wo_display": (("lens", "resample"), False),
    "wo_resample": (("lens", "display"), False),
    "state_blind": (("lens", "resample", "display"), True),
    "wo_foveation": (("lens", "resample", "display"), False),
}
#: ablation -> the downstream effect it leaves out: trained among all ablations only when that effect is on
ABLATION_EFFECT: dict[str, str] = {"wo_foveation": "foveation"}


def ablations_for(effects: Iterable[str]) -> tuple[str, ...]:
    """The ablations a run through the downstream ``effects`` (stage names) trains when all are asked for."""
    on = set(effects)
    return tuple(a for a in ABLATIONS if a not in ABLATION_EFFECT or ABLATION_EFFECT[a] in on)
