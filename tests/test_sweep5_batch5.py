"""Mutation sweep 5, batch 5: behaviours that a plausible one-line bug changed and no test observed
(``trust_code=True`` reaches a Scaffold-GS folder's appearance embedding; the bank generator's recorded pupil
coverage; ``ladder_len``'s coarse ladder; the byte named for a truncated last 3D-point track; the dtype of a
bank's default transmission). See docs/testing.md."""

from __future__ import annotations

import math
import struct
import warnings

import numpy as np
import pytest
import torch
from torch import nn

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.scaffold_io import load_scaffold_dir, save_scaffold_dir
from controlgs_adapter.datasets.colmap import _read_points_bin
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.generate import build_bank
from controlgs_adapter.downstream.optics.resampled import ladder_len
from controlgs_adapter.errors import FileFormatError

F64 = torch.float64


# ------------------------------------------------------------------ trust_code and embedding_appearance.pt
class _OddEmbedding(nn.Module):
    """Scaffold-GS's appearance embedding wrapper with one exported method besides ``forward``: outside the
    subset the data reader takes (a class with methods besides ``forward``), harmless."""

    def __init__(self, weight: torch.Tensor) -> None:
        super().__init__()
        self.embedding = nn.Embedding.from_pretrained(weight.clone(), freeze=False)

    def forward(self, idx: torch.Tensor) -> torch.Tensor:
        return self.embedding(idx)

    @torch.jit.export
    def extra(self) -> int:
        return 1


def test_trust_code_reaches_the_appearance_embedding_of_a_split_scaffold_folder(tmp_path):
    """``load_scaffold_dir(..., trust_code=True)`` docstring: TorchScript files outside the supported subset
    are read with ``torch.jit.load``; by default they are refused. That holds for ``embedding_appearance.pt``
    as for the decoders: the trusted load returns the weights this test wrote."""
    torch.manual_seed(0)
    model = NeuralGaussianModel(12, feat_dim=8, n_offsets=3, appearance_dim=4, num_cameras=5)
    it = save_scaffold_dir(model, tmp_path / "m", iteration=2)
    weight = torch.randn(5, 4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.jit.script(_OddEmbedding(weight)).save(str(it / "embedding_appearance.pt"))
    with pytest.raises(FileFormatError, match="embedding_appearance.pt"):
        load_scaffold_dir(tmp_path / "m")  # read as data by default: refused, nothing run
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        trusted = load_scaffold_dir(tmp_path / "m", trust_code=True)
    assert torch.equal(trusted.embedding_appearance.embedding.weight.detach(), weight)


# ------------------------------------------------------------------ build_bank: min_pupil_coverage
def test_recorded_pupil_coverage_is_a_fraction_at_most_one_rounded_to_5_decimals():
    """``build_bank`` docstring: ``meta["generator"]["min_pupil_coverage"]`` is at most 1 and rounded to 5
    decimals. On axis with 8 pupil samples the rim-cell quadrature sums to ~1.0005 of the disc (full
    coverage: reads 1.0); with 16 it sums to ~0.99989 (the 6th decimal is not 0, so the rounding shows)."""
    over = build_bank(grid=(1, 1), psf_size=5, pupil_samples=8, chief_grid=(2, 2))
    assert over.meta["generator"]["min_pupil_coverage"] == 1.0
    under = build_bank(grid=(1, 1), psf_size=5, pupil_samples=16, chief_grid=(2, 2))
    cov = under.meta["generator"]["min_pupil_coverage"]
    assert 0.999 < cov < 1.0 and cov == round(cov, 5)


# ------------------------------------------------------------------ ladder_len
def _is_7_smooth(m: int) -> bool:
    for p in (2, 3, 5, 7):
        while m % p == 0:
            m //= p
    return m == 1


def test_ladder_len_rounds_up_to_a_coarse_ladder_of_fast_fft_sizes():
    """``ladder_len`` docstring: ``n`` rounded up to a coarse ladder of fast FFT sizes (factors 2, 3, 5, 7),
    in steps of ~12 %, so nearby lengths share one size. Up to 16384 a ladder growing by 1.12 per step from
    1 has at most log(16384) / log(1.12) + 1 ~ 86.6 rungs; every fast size (there are 400 up to 16384 by
    brute force) would be far more."""
    n_max = 16384
    sizes = {}
    for n in range(1, n_max + 1):
        m = ladder_len(n)
        assert m >= n and _is_7_smooth(m), (n, m)
        sizes.setdefault(m, n)
    assert len(sizes) <= math.log(n_max) / math.log(1.12) + 1
    assert sum(_is_7_smooth(m) for m in range(1, n_max + 1)) == 400  # the brute-force count quoted above
    ladder = sorted(sizes)
    for lo, hi in zip(ladder, ladder[1:]):  # monotone: every n between two rungs takes the upper one
        assert ladder_len(lo + 1) == hi and ladder_len(hi) == hi


# ------------------------------------------------------------------ COLMAP points3D.bin
def test_truncated_track_of_the_last_3d_point_names_that_record_s_byte(tmp_path):
    """COLMAP's points3D.bin layout (u64 count; per point u64 id, 3 f64 xyz, 3 u8 rgb, f64 error, u64 track
    length, then (u32 image_id, u32 point2D_idx) per track element): a record is 51 + 8 * track bytes.
    The first point (track 2) is 67 bytes at byte 8, so the second starts at byte 75; it declares a track
    of 3 but holds 2: the file is 8 + 67 + 51 + 16 = 142 bytes and the error names byte 75."""
    first = (struct.pack("<Q3d", 1, 0.5, 1.5, 2.5) + bytes([1, 2, 3]) + struct.pack("<dQ", 0.1, 2)
             + struct.pack("<4I", 1, 0, 2, 0))
    second = (struct.pack("<Q3d", 2, -1.0, 0.0, 1.0) + bytes(3) + struct.pack("<dQ", 0.2, 3)
              + struct.pack("<4I", 1, 1, 2, 1))
    p = tmp_path / "points3D.bin"
    p.write_bytes(struct.pack("<Q", 2) + first + second)
    assert p.stat().st_size == 142
    with pytest.raises(FileFormatError, match=r"points3D.bin: truncated COLMAP binary file: the track of 3D point 1 "
                                              r"at byte 75 runs past the end \(142 bytes\)"):
        _read_points_bin(p)
    p.write_bytes(struct.pack("<Q", 2) + first + second + struct.pack("<2I", 3, 2))  # the whole track: reads
    assert np.array_equal(_read_points_bin(p), [[0.5, 1.5, 2.5], [-1.0, 0.0, 1.0]])


# ------------------------------------------------------------------ PSFBank.transmission
def test_default_transmission_is_float64_ones_like_a_recorded_one():
    """``PSFBank.transmission`` docstring: ``[L, Gy, Gx]`` float64; ones if the bank records none (the
    same dtype as a recorded ``meta["transmission"]`` and as the bank's own tables)."""
    L, G, K = 3, 2, 3
    psf = torch.zeros(L, G, G, K, K, dtype=F64)
    psf[..., K // 2, K // 2] = 1.0
    c = torch.linspace(-1, 1, 3, dtype=F64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = torch.tensor([-0.5, 0.5], dtype=F64)
    args = dict(psf=psf, psf_pitch_mm=torch.full((L, G, G), 0.1, dtype=F64), field_x=f, field_y=f,
                chief=torch.stack([cx, cy], -1).expand(L, 3, 3, 2).clone(), chief_x=c, chief_y=c,
                wavelengths_nm=(656.0, 550.0, 486.0), display_mm=(10.0, 10.0))
    plain = PSFBank(**args).transmission
    assert plain.dtype == F64 and torch.equal(plain, torch.ones(L, G, G, dtype=F64))
    recorded = PSFBank(**args, meta={"transmission": [[[0.5] * G] * G] * L}).transmission
    assert recorded.dtype == plain.dtype == psf.dtype
