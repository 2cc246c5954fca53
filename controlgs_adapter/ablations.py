"""The paper's ablations (Tbl. 4): which condition modules each trains and whether it is state-blind.

Shared by training (``controlgs train`` / ``demo``), evaluation, the viewer and the report.
"""

from __future__ import annotations

__all__ = ["ABLATIONS"]

#: ablation name -> (modules trained, state_blind), paper Tbl. 4
ABLATIONS: dict[str, tuple[tuple[str, ...], bool]] = {
    "wo_lens": (("resample", "display"), False),
    "wo_display": (("lens", "resample"), False),
    "wo_resample": (("lens", "display"), False),
    "state_blind": (("lens", "resample", "display"), True),
}
