"""The multi-seed report: rows that do not depend on the seed (the backbone without and with supersampling,
the ideal render) show their value alone, the trained adapters mean ± std over the seeds."""

from __future__ import annotations

import torch

from controlgs_adapter.evaluation import IDEAL, GridResult
from controlgs_adapter.report import markdown_tables, seed_independent

GRID = ((1.0, 2.0), (0.0, 0.5))


def _result(seed: int, values: dict[str, float]) -> GridResult:
    per_view = {m: {"psnr": torch.full((2, 2, 3), v, dtype=torch.float64),
                    "ssim": torch.full((2, 2, 3), v / 100.0, dtype=torch.float64)} for m, v in values.items()}
    return GridResult(*GRID, per_view, info={"seed": seed})


def test_seed_independent_rows_show_the_value_alone():
    runs = [_result(0, {"no_ss": 18.0, "ss": 20.0, IDEAL: 20.5, "controlgs": 21.0, "wo_lens": 20.9}),
            _result(1, {"no_ss": 18.0, "ss": 20.0, IDEAL: 20.5, "controlgs": 21.2, "wo_lens": 20.9})]
    assert seed_independent(runs) == {"no_ss", "ss", IDEAL, "wo_lens"}
    md = markdown_tables(runs)
    assert "| Backbone (no SS) | 18.00 | 0.1800 |" in md
    assert "| SS-backbone | 20.00 | 0.2000 |" in md
    assert "| Ideal render (GT through E_s) | 20.50 | 0.2050 |" in md
    assert "| ControlGS | **21.10 ± 0.14** | **0.2110 ± 0.0014** |" in md
    assert "| w/o Lens | 20.90 | 0.2090 |" in md  # the same in both seeds: it did not depend on them either
    assert "± 0.00 " not in md and "± 0.0000 " not in md
    assert "Rows without ± (Backbone (no SS), SS-backbone, Ideal render (GT through E_s), w/o Lens) do not depend on the seed" in md


def test_one_seed_has_no_spread_and_no_note():
    run = _result(0, {"ss": 20.0, "controlgs": 21.0})
    assert seed_independent([run]) == set()
    md = markdown_tables(run)
    assert "±" not in md and "Rows without" not in md


def test_a_row_differing_in_one_metric_keeps_its_spread():
    a = _result(0, {"ss": 20.0, "controlgs": 21.0})
    b = _result(1, {"ss": 20.0, "controlgs": 21.0})
    b.per_view["controlgs"]["ssim"] = b.per_view["controlgs"]["ssim"] + 0.01
    assert seed_independent([a, b]) == {"ss"}
    assert "| ControlGS | **21.00 ± 0.00** | **0.2150 ± 0.0071** |" in markdown_tables([a, b])
