"""In-memory models of the anchor families (HAC++, ContextGS, Octree-GS, CompGS), built from the arrays of
the ``*_files`` helpers, at positions and scales a test chooses."""

from __future__ import annotations

import helpers.compgs_files as compgs_files
import helpers.contextgs_files as contextgs_files
import helpers.hac_files as hac_files
import helpers.octree_files as octree_files
import torch

from controlgs_adapter.backends.compgs import CompGSModel
from controlgs_adapter.backends.contextgs import ContextGSModel
from controlgs_adapter.backends.hac import HACModel
from controlgs_adapter.backends.octree_gs import OctreeGSModel


def hac_kwargs(n_mask_cols: int, seed: int = 0) -> dict:
    """Keyword arguments of a decoded HAC++ / HAC model (``mask`` with ``n_mask_cols`` columns), no voxel size."""
    arr = hac_files._arrays(seed, decoded=True, mask_cols=n_mask_cols)
    return dict(anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                mask=torch.from_numpy(arr["mask"])[:, :, None], anchor_feat=torch.from_numpy(arr["feat"]),
                scaling=torch.from_numpy(arr["scale"]), decoded_version=True, **hac_files._decoders(seed))


def family_kwargs() -> list[tuple[type, dict, list[str]]]:
    """(class, keyword arguments, the per-anchor tensor arguments) of a model of each family."""
    hac = (HACModel, {"voxel_size": 0.01, **hac_kwargs(hac_files.K + 1)}, ["anchor", "offset", "mask", "anchor_feat", "scaling"])
    t = {k: torch.from_numpy(v) for k, v in contextgs_files._arrays(0, decoded=True).items()}
    ctx = (ContextGSModel, dict(anchor=t["anchor"], offset=t["offset"], mask=t["mask"][:, :, None], anchor_feat=t["feat"],
                                scaling=t["scale"], hyper_latent=t["hyper"], decoded_version=True,
                                **contextgs_files._decoders(0)),
           ["anchor", "offset", "mask", "anchor_feat", "scaling", "hyper_latent"])
    oa = octree_files._arrays(0)
    octo = (OctreeGSModel, dict(anchor=torch.from_numpy(oa["anchor"]), offset=torch.from_numpy(oa["offset"]),
                                anchor_feat=torch.from_numpy(oa["feat"]), scaling=torch.from_numpy(oa["scale"]),
                                level=torch.from_numpy(oa["level"][:, None]), extra_level=torch.from_numpy(oa["extra"]),
                                voxel_size=0.1, standard_dist=3.0,
                                **octree_files._decoders(torch.Generator().manual_seed(0))),
            ["anchor", "offset", "anchor_feat", "scaling", "level", "extra_level"])
    ca = compgs_files._arrays(0)
    comp = (CompGSModel, dict(means=torch.from_numpy(ca["means"]), scales_before_exp=torch.from_numpy(ca["scales"]),
                              ref_feats=torch.from_numpy(ca["ref"]), res_feats=torch.from_numpy(ca["res"])),
            ["means", "scales_before_exp", "ref_feats", "res_feats"])
    return [hac, ctx, octo, comp]


def models_at(pos: torch.Tensor, linear_scales: torch.Tensor) -> dict[str, torch.nn.Module]:
    """A model of each family with anchors at ``pos`` ``[n, 3]`` and the linear scales ``[n, 6]``, stored as
    each family stores them (log scales for CompGS and Octree-GS, linear for decoded HAC++ and ContextGS),
    every offset on, level 0, no rotation given: ``{backend name: model}``."""
    n = pos.shape[0]
    ca = compgs_files._arrays(0)
    comp = CompGSModel(means=pos, scales_before_exp=linear_scales.log(), ref_feats=torch.from_numpy(ca["ref"][:n]),
                       res_feats=torch.from_numpy(ca["res"][:n]))
    ha = hac_files._arrays(0, decoded=True, mask_cols=hac_files.K + 1, n=n)
    hac = HACModel(voxel_size=0.001, decoded_version=True, anchor=pos, offset=torch.from_numpy(ha["offset"]),
                   mask=torch.ones(n, hac_files.K + 1, 1), anchor_feat=torch.from_numpy(ha["feat"]), scaling=linear_scales,
                   **hac_files._decoders(0))
    xa = {k: torch.from_numpy(v[:n]) for k, v in contextgs_files._arrays(0, decoded=True).items()}
    ctx = ContextGSModel(anchor=pos, offset=xa["offset"], mask=torch.ones(n, contextgs_files.K, 1), anchor_feat=xa["feat"],
                         scaling=linear_scales, hyper_latent=xa["hyper"], decoded_version=True, **contextgs_files._decoders(0))
    oa = octree_files._arrays(0)
    octo = OctreeGSModel(anchor=pos, offset=torch.from_numpy(oa["offset"][:n]), anchor_feat=torch.from_numpy(oa["feat"][:n]),
                         scaling=linear_scales.log(), level=torch.zeros(n, 1, dtype=torch.int32), extra_level=torch.zeros(n),
                         voxel_size=0.1, standard_dist=3.0, **octree_files._decoders(torch.Generator().manual_seed(0)))
    return {"compgs": comp, "hac": hac, "contextgs": ctx, "octree_gs": octo}
