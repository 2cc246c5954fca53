"""The report's findings ('What the numbers show') on a GridResult built from known numbers: wins,
ties, worst cells and means counted by hand, for a higher-is-better and a lower-is-better metric."""

from __future__ import annotations

import torch

from controlgs_adapter.evaluation import GridResult
from controlgs_adapter.report import markdown_tables


def test_findings_count_strict_wins_ties_and_worst_cells_by_hand():
    """2 x 3 grid, one view. PSNR ControlGS - SS per cell: +1, 0, 0, -0.5, +2, 0 -> 2 wins of 6 (ties are
    not wins), mean +0.4167, worst -0.5. FLIP (lower is better) ControlGS - SS: -0.1, 0, +0.2, 0, 0, 0 ->
    1 win; printed in FLIP units: mean +0.01667, worst cell +0.2. SS vs no-SS PSNR: +1 in 4 cells, equal in 2."""
    ss_psnr = torch.full((2, 3, 1), 20.0, dtype=torch.float64)
    cg_psnr = ss_psnr + torch.tensor([[1.0, 0.0, 0.0], [-0.5, 2.0, 0.0]], dtype=torch.float64)[..., None]
    ss_flip = torch.full((2, 3, 1), 0.5, dtype=torch.float64)
    cg_flip = ss_flip - torch.tensor([[0.1, 0.0, -0.2], [0.0, 0.0, 0.0]], dtype=torch.float64)[..., None]
    no_ss_psnr = ss_psnr - torch.tensor([[0.0, 1.0, 1.0], [0.0, 1.0, 1.0]], dtype=torch.float64)[..., None]
    result = GridResult((1.0, 2.0), (0.0, 0.2, 0.4), {
        "no_ss": {"psnr": no_ss_psnr, "flip": ss_flip.clone()},
        "ss": {"psnr": ss_psnr, "flip": ss_flip},
        "controlgs": {"psnr": cg_psnr, "flip": cg_flip}})
    md = markdown_tables(result)
    assert ("- PSNR: ControlGS better than SS-backbone in 2/6 settings (mean difference +0.4167, worst cell -0.5)."
            in md), md
    assert "- FLIP: ControlGS better than SS-backbone in 1/6 settings (mean difference +0.01667, worst cell +0.2)." in md, md
    assert ("- PSNR: SS-backbone better than no-SS in 4/6 settings, equal in 2 (at d = 1 both render at S) "
            "(mean difference +0.6667)." in md), md
    # Tbl. 1: the best mean in bold (highest PSNR, lowest FLIP; ties all bold). Means by hand: PSNR 19.33,
    # 20, 20.42; FLIP 0.5, 0.5, 3.1 / 6 = 0.5167
    assert "| Backbone (no SS) | 19.33 | **0.5000** |" in md, md
    assert "| SS-backbone | 20.00 | **0.5000** |" in md and "| ControlGS | **20.42** | 0.5167 |" in md, md


def test_difference_tables_appear_with_exactly_the_two_methods():
    """A result holding only ``ss`` and ``controlgs`` gets the per-setting ControlGS-minus-SS table, its
    cells the differences by hand, signed."""
    ss = torch.full((1, 2, 1), 20.0, dtype=torch.float64)
    cg = ss + torch.tensor([[0.5, -0.25]], dtype=torch.float64)[..., None]
    md = markdown_tables(GridResult((1.0,), (0.0, 0.4), {"ss": {"psnr": ss}, "controlgs": {"psnr": cg}}))
    section = md.split("PSNR of ControlGS minus SS-backbone:", 1)[1].split("\n\n", 2)[1]
    assert "+0.50" in section and "-0.25" in section, section
