"""A small mutation sample (not run in CI): apply plausible one-line bugs, one at a time, to a copy of
the library in a temporary git worktree of HEAD, run the test files that cover the site, and report
which mutations the tests caught. Results are recorded in docs/testing.md.

    .venv/bin/python scripts/mutation_sample.py [--only ID ...] [--worktree /tmp/mut]

The worktree is imported instead of this checkout (the editable install's package mapping is
pointed at it for each run) and removed at the end.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Mutation:
    id: str
    path: str
    old: str
    new: str
    tests: tuple[str, ...]
    what: str


FAMILY_TESTS = ("tests/test_by_hand_decodes.py", "tests/test_backend_octree_gs.py", "tests/test_backend_hac.py",
                "tests/test_backend_contextgs.py", "tests/test_backend_compgs.py", "tests/test_reference_model.py")
PLACEMENT_TESTS = ("tests/test_display_mapping.py", "tests/test_options_by_hand.py", "tests/test_stages_lens.py")
DATASET_TESTS = ("tests/test_datasets_colmap.py", "tests/test_datasets_blender_ngp.py", "tests/test_datasets_sanity_detect.py")

MUTATIONS: tuple[Mutation, ...] = (
    # --- the seven of issue 15, section 5 (kept to show they are caught now)
    Mutation("i1", "controlgs_adapter/state.py", "[[fx, 0.0, w / 2.0], [0.0, fy, h / 2.0]",
             "[[fx, 0.0, (w - 1) / 2.0], [0.0, fy, (h - 1) / 2.0]", ("tests/test_camera_scaffold.py",),
             "from_scaffold principal point at (w-1)/2"),
    Mutation("i2", "downstream/display.py", "float] = (228.52, 205.66, 567.64)", "float] = (205.66, 228.52, 567.64)",
             ("tests/test_regressions.py", "tests/test_stages_display.py"), "display power coefficients R and G swapped"),
    Mutation("i3", "controlgs_adapter/injector.py", "key = (width, torch.is_grad_enabled())", "key = (width, False)",
             ("tests/test_regressions.py", "tests/test_controlgs.py"), "injection cache key without grad mode"),
    Mutation("i4", "downstream/display.py", "        power_ref = power.detach()\n    target", "        power_ref = power\n    target",
             ("tests/test_regressions.py", "tests/test_stages_display.py"), "P_ref without reference not detached"),
    Mutation("i5", "downstream/pipeline.py", "pos = result.index(chain[-1]) + 1", "pos = result.index(chain[0]) + 1",
             ("tests/test_regressions.py", "tests/test_pipeline.py"), "stages after the same stage: reversed order"),
    Mutation("i6", "controlgs_adapter/formats/backbone.py", 'order = "<" if fmt == "binary_little_endian" else ">"', 'order = "<"',
             ("tests/test_regressions.py", "tests/test_formats.py"), "big-endian PLY read as little-endian"),
    Mutation("i7", "controlgs_adapter/evaluation.py", "e, g = eye.detach().clamp(0.0, 1.0).double(), gt.double()",
             "e, g = eye.detach().double(), gt.double()", ("tests/test_regressions.py",), "no clamp before the metrics"),
    # --- other sites
    Mutation("m1", "controlgs_adapter/state.py", "        k[0] *= w / self.width\n", "        k[0] *= h / self.height\n",
             ("tests/test_state.py", "tests/test_camera_scaffold.py"), "Camera.scaled: x intrinsics scaled by the height ratio"),
    Mutation("m2", "controlgs_adapter/state.py", "[0.0, 2.0 / self.height, -1.0]", "[0.0, 2.0 / self.width, -1.0]",
             ("tests/test_state.py", "tests/test_regressions.py", "tests/test_schedules.py"),
             "normalized_screen: y normalised by the width"),
    Mutation("m3", "controlgs_adapter/schedules.py", "        return math.log2(state.downsample)",
             "        return math.log(state.downsample)", ("tests/test_schedules.py", "tests/test_regressions.py"),
             "resample control ln(d) instead of log2(d)"),
    Mutation("m4", "controlgs_adapter/schedules.py", "        return min(max((alpha - self.lo) / (self.hi - self.lo), 0.0), 1.0)",
             "        return min(max((alpha - self.lo) / (self.hi - self.lo), 0.0), 2.0)",
             ("tests/test_schedules.py", "tests/test_regressions.py"), "scalar strength clamped at 2, not 1"),
    Mutation("m5", "downstream/display.py", "    emitted = linear.clamp(min=0.0)", "    emitted = linear",
             ("tests/test_stages_display.py", "tests/test_display_mapping.py", "tests/test_regressions.py"),
             "negative light counted in the power"),
    Mutation("m6", "downstream/display.py", "    out = dimmed.clamp(0.0, 1.0)", "    out = dimmed",
             ("tests/test_stages_display.py", "tests/test_display_mapping.py"), "display output not clipped"),
    Mutation("m7", "downstream/display.py", "        scale = scale.clamp(max=1.0)", "        scale = scale.clamp(min=1.0)",
             ("tests/test_stages_display.py", "tests/test_display_mapping.py"), "brighten=False clamps the wrong side"),
    Mutation("m8", "downstream/color.py", "_GAMMA = 2.4", "_GAMMA = 2.2", ("tests/test_stages_color.py",),
             "sRGB exponent 2.2"),
    Mutation("m9", "controlgs_adapter/metrics.py", "c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2",
             "c1, c2 = (0.03 * data_range) ** 2, (0.01 * data_range) ** 2", ("tests/test_metrics.py",),
             "SSIM constants swapped"),
    Mutation("m10", "controlgs_adapter/losses.py", "    loss = weights.l1 * diff.abs().mean() + weights.mse * diff.square().mean()",
             "    loss = weights.l1 * diff.abs().mean() + weights.mse * diff.abs().mean()",
             ("tests/test_training.py", "tests/test_metrics.py"), "MSE term computed as L1"),
    Mutation("m11", "controlgs_adapter/injector.py", "                z[:, j] *= lam.to(z.dtype).unsqueeze(-1)",
             "                pass", ("tests/test_controlgs.py",), "per-anchor strength ignored"),
    Mutation("m12", "controlgs_adapter/injector.py", "                w = w * lam", "                w = w",
             ("tests/test_controlgs.py",), "shared strength ignored"),
    Mutation("m13", "controlgs_adapter/controlgs.py", "bool(((ids < 0) | (ids >= a)).any())", "bool(((ids < 0) | (ids > a)).any())",
             ("tests/test_controlgs.py", "tests/test_bad_inputs.py"), "anchor id == A accepted (off by one)"),
    Mutation("m14", "backends/hac.py", "    return torch.round(anchor / voxel_size) * voxel_size",
             "    return torch.floor(anchor / voxel_size) * voxel_size", ("tests/test_backend_hac.py",),
             "HAC voxel snap floors instead of rounding"),
    Mutation("m15", "backends/contextgs.py", "    levels = 2 ** ANCHOR_BITS - 1", "    levels = 2 ** ANCHOR_BITS",
             ("tests/test_backend_contextgs.py",), "ContextGS anchor quantisation: 2^16 levels"),
    Mutation("m16", "backends/octree_gs.py", "self._level.squeeze(1) <= self.map_to_int_level(",
             "self._level.squeeze(1) < self.map_to_int_level(", ("tests/test_backend_octree_gs.py",),
             "Octree LOD mask drops the selected level"),
    Mutation("m17", "backends/compgs.py", "        return anchor_ids.repeat_interleave(rows_per_anchor)",
             "        return anchor_ids.repeat(rows_per_anchor)", ("tests/test_backend_compgs.py",),
             "CompGS rows -> anchors tiled instead of grouped"),
    Mutation("m18", "controlgs_adapter/formats/backbone.py", "return np.ascontiguousarray(flat.reshape(-1, 3, n_offsets).transpose(0, 2, 1))",
             "return np.ascontiguousarray(flat.reshape(-1, n_offsets, 3))", ("tests/test_scaffold_io.py",),
             "Scaffold PLY offsets read without the transpose"),
    Mutation("m19", "backends/models/anchor_model.py", "scales=s[:, 3:] * torch.sigmoid(scale_rot[flat, :3]),",
             "scales=s[:, :3] * torch.sigmoid(scale_rot[flat, :3]),",
             ("tests/test_backend_hac.py", "tests/test_backend_contextgs.py", "tests/test_backend_octree_gs.py"),
             "family Gaussians scaled by the offset scales"),
    Mutation("m20", "backends/hac.py", "    return True if bool((scales >= 0).all()) else None",
             "    return True if bool((scales > 0).all()) else None", ("tests/test_backend_hac.py",),
             "decoded detection requires scales > 0"),
    Mutation("m21", "controlgs_adapter/training.py",
             'd = math.exp(float(u[0]) * math.log(c.max_downsample)) if "resample" in self.pipeline else 1.0',
             'd = 1.0 + float(u[0]) * (c.max_downsample - 1.0) if "resample" in self.pipeline else 1.0',
             ("tests/test_training.py",), "downsample sampled uniformly, not log-uniformly"),
    Mutation("m22", "controlgs_adapter/metrics.py", "    mse = (x - y).square().mean(dim=(-3, -2, -1))",
             "    mse = (x - y).square().mean(dim=(-2, -1)).sum(-1)", ("tests/test_metrics.py",),
             "PSNR: MSE summed over channels"),
    Mutation("m23", "backends/contextgs.py", "        rot = self.prefilter_rotation.to(self._rotation).expand(self._anchor.shape[0], 4)",
             "        rot = self._rotation", ("tests/test_backend_contextgs.py",),
             "ContextGS prefilter with each anchor's rotation"),
    # --- a second sample at other sites (session 3): datasets, placement, losses, report, OLED, state
    Mutation("m24", "controlgs_adapter/datasets/colmap.py", "k, d = (p[0], p[0], p[1], p[2]), (p[3], 0.0, 0.0, 0.0, 0.0)",
             "k, d = (p[0], p[0], p[1], p[2]), (0.0, p[3], 0.0, 0.0, 0.0)", ("tests/test_datasets_colmap.py",),
             "COLMAP SIMPLE_RADIAL k read as k2"),
    Mutation("m25", "controlgs_adapter/datasets/colmap.py", "(p[4], p[5], p[6], p[7], 0.0)", "(p[4], p[5], p[7], p[6], 0.0)",
             ("tests/test_datasets_colmap.py",), "COLMAP OPENCV p1, p2 swapped"),
    Mutation("m26", "controlgs_adapter/datasets/colmap.py", "[0.0, fy * sy, cy * sy]", "[0.0, fy * sx, cy * sy]",
             ("tests/test_datasets_colmap.py",), "COLMAP fy scaled by the width ratio"),
    Mutation("m27", "controlgs_adapter/datasets/colmap.py", "[2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],",
             "[2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],", ("tests/test_datasets_colmap.py",),
             "quaternion -> rotation: one sign wrong"),
    Mutation("m28", "controlgs_adapter/datasets/colmap.py", "if all(max(image_size(d / nm)) >= resolution for nm in names):",
             "if all(min(image_size(d / nm)) >= resolution for nm in names):", ("tests/test_datasets_colmap.py",),
             "images_N picked by the shorter side"),
    Mutation("m29", "controlgs_adapter/datasets/colmap.py",
             "test = [f for i, f in enumerate(frames) if holdout and i % holdout == 0]",
             "test = [f for i, f in enumerate(frames) if holdout and i % holdout == 1]", ("tests/test_datasets_colmap.py",),
             "COLMAP holdout takes the wrong frames"),
    Mutation("m30", "controlgs_adapter/datasets/blender.py", "[[f, 0.0, w / 2.0], [0.0, f, h / 2.0]", "[[f, 0.0, w / 2.0], [0.0, f, w / 2.0]",
             ("tests/test_datasets_blender_ngp.py",), "Blender cy from the width"),
    Mutation("m31", "controlgs_adapter/datasets/blender.py", "_GL_TO_CV = np.diag([1.0, -1.0, -1.0])",
             "_GL_TO_CV = np.diag([-1.0, 1.0, -1.0])", ("tests/test_datasets_blender_ngp.py",), "OpenGL -> OpenCV flips x, not y"),
    Mutation("m32", "controlgs_adapter/datasets/images.py",
             "img = img[:3] * a + background.to(img).view(3, 1, 1) * (1.0 - a)",
             "img = img[:3] + background.to(img).view(3, 1, 1) * (1.0 - a)", ("tests/test_datasets_blender_ngp.py",),
             "RGBA treated as premultiplied"),
    Mutation("m33", "controlgs_adapter/datasets/images.py",
             "ys = (torch.arange(h, dtype=torch.float64, device=image.device) + 0.5 - cy) / fy",
             "ys = (torch.arange(h, dtype=torch.float64, device=image.device) - cy) / fy",
             ("tests/test_datasets_colmap.py", "tests/test_datasets_blender_ngp.py"), "undistort: row centres at i, not i + 0.5"),
    Mutation("m34", "downstream/placement.py", "if width * dh >= height * dw:", "if width * dw >= height * dh:",
             ("tests/test_display_mapping.py", "tests/test_pipeline.py", "tests/test_regressions.py"),
             "fit placement: width-limited test with the display's sides swapped"),
    Mutation("m35", "downstream/placement.py", "return ImageRegion((width / height) * (dh / dw), 1.0,",
             "return ImageRegion((height / width) * (dh / dw), 1.0,",
             ("tests/test_display_mapping.py", "tests/test_pipeline.py", "tests/test_regressions.py"),
             "fit placement of a portrait image: inverse aspect"),
    Mutation("m36", "controlgs_adapter/losses.py",
             "loss = weights.l1 * diff.abs().mean() + weights.mse * diff.square().mean()",
             "loss = weights.l1 * diff.abs().mean() + weights.l1 * diff.square().mean()", ("tests/test_metrics.py",),
             "MSE term weighted by the L1 weight"),
    Mutation("m37", "controlgs_adapter/losses.py", "ssim(pred, target, data_range=1.0)", "ssim(pred, target, data_range=255.0)",
             ("tests/test_metrics.py",), "loss SSIM with data_range 255"),
    Mutation("m38", "controlgs_adapter/report.py", '"std": float(vals.std()) if len(vals) > 1 else 0.0',
             '"std": float(vals.std(unbiased=False)) if len(vals) > 1 else 0.0', ("tests/test_report_honest.py",),
             "seed std with ddof 0"),
    Mutation("m39", "downstream/oled.py", 'mode="nearest-exact"', 'mode="nearest"',
             ("tests/test_pipeline.py", "tests/test_stages_resample.py"), "OLED sampling with nearest (floor) indices"),
    Mutation("m40", "controlgs_adapter/state.py", "if not math.isfinite(rho) or not (0.0 <= rho < 1.0):",
             "if not math.isfinite(rho) or not (0.0 <= rho <= 1.0):", ("tests/test_state.py", "tests/test_bad_inputs.py"),
             "power_saving = 1 accepted"),
    Mutation("m41", "controlgs_adapter/state.py", "return (pc[:, :2] / z).masked_fill_(z <= 0, float(\"inf\"))",
             "return (pc[:, :2] / z).masked_fill_(z < 0, float(\"inf\"))", ("tests/test_state.py", "tests/test_camera_scaffold.py"),
             "points at depth 0 projected as finite"),
    Mutation("m42", "controlgs_adapter/metrics.py", "return 10.0 * torch.log10(data_range**2 / mse)",
             "return 10.0 * torch.log10(data_range / mse)", ("tests/test_metrics.py",), "PSNR with data_range not squared"),
    Mutation("m43", "controlgs_adapter/perceptual.py", "feats = self.features(((2.0 * both - 1.0) - self.shift) / self.scale)",
             "feats = self.features((both - self.shift) / self.scale)", ("tests/test_metrics.py", "tests/test_report_honest.py"),
             "LPIPS input not mapped to [-1, 1]"),
    Mutation("m44", "controlgs_adapter/datasets/sanity.py", "if 2 * len(blind) > len(frames):", "if len(blind) > len(frames):",
             ("tests/test_datasets_sanity_detect.py",), "axis-flip check needs every view blind"),
    Mutation("m45", "controlgs_adapter/datasets/instant_ngp.py",
             "test = [f for j, f in enumerate(frames) if holdout and j % holdout == 0]",
             "test = [f for j, f in enumerate(frames) if holdout and j % holdout == holdout - 1]",
             ("tests/test_datasets_blender_ngp.py",), "instant-ngp holdout takes the wrong frames"),
    # --- a third sample (session 3): resampling, lens, schedules, injector, adapter file, colour, datasets
    Mutation("m46", "downstream/resample.py", "first = torch.floor(lo).long()", "first = torch.round(lo).long()",
             ("tests/test_stages_resample.py",), "area filter taps start at the nearest, not the covering, pixel"),
    Mutation("m47", "downstream/resample.py", "return max(1, round(size[0] / d)), max(1, round(size[1] / d))",
             "return max(1, int(size[0] / d)), max(1, int(size[1] / d))", ("tests/test_stages_resample.py", "tests/test_pipeline.py"),
             "resampled size floored instead of rounded"),
    Mutation("m48", "downstream/lens.py", "r2 = ((p * aspect) ** 2).sum(-1)", "r2 = (p ** 2).sum(-1)",
             ("tests/test_stages_lens.py", "tests/test_pipeline.py", "tests/test_regressions.py"),
             "radial pre-warp ignores the image's placement (non-square)"),
    Mutation("m49", "downstream/lens.py", "powers = r2[None] ** torch.arange(1, k.shape[1] + 1,",
             "powers = r2[None] ** torch.arange(0, k.shape[1],", ("tests/test_stages_lens.py",),
             "radial coefficients applied to r^0, r^2 ... instead of r^2, r^4 ..."),
    Mutation("m50", "controlgs_adapter/schedules.py", "return ((alpha - self.lo) / (self.hi - self.lo)).clamp(0.0, 1.0)",
             "return ((alpha - self.lo) / (self.hi - self.lo)).clamp(min=0.0)", ("tests/test_schedules.py",),
             "per-anchor strength not clamped at 1"),
    Mutation("m51", "controlgs_adapter/injector.py", "if hit is not None and hit[0] == versions:", "if hit is not None:",
             ("tests/test_controlgs.py", "tests/test_regressions.py", "tests/test_training.py"),
             "injection cache not invalidated by an in-place parameter update"),
    Mutation("m52", "controlgs_adapter/injector.py", "            z = z[:, cols]", "            z = z[:, :len(cols)]",
             ("tests/test_controlgs.py", "tests/test_regressions.py"), "a subset of modules takes the first condition columns"),
    Mutation("m53", "controlgs_adapter/formats/adapter.py",
             "if ids.numel() == saved and backend.fingerprint(model, ids) == want:", "if ids.numel() == saved:",
             ("tests/test_adapter_io.py", "tests/test_adapter_names.py", "tests/test_backend_contextgs.py"),
             "adapter rows scattered onto valid anchors without checking their fingerprint"),
    Mutation("m54", "downstream/color.py", "_DECODE_THRESHOLD = 0.04045", "_DECODE_THRESHOLD = 0.0031308",
             ("tests/test_stages_color.py",), "sRGB decode threshold from the encode side"),
    Mutation("m55", "controlgs_adapter/evaluation.py", "return float(self.per_view[method][metric].mean())",
             "return float(self.per_view[method][metric].mean(dim=-1).mean(dim=-1).max())",
             ("tests/test_public_api.py", "tests/test_report_honest.py", "tests/test_demo.py"), "GridResult.mean takes the best row, not the mean"),
    Mutation("m56", "controlgs_adapter/datasets/base.py", "return max(1, round(width / f)), max(1, round(height / f))",
             "return max(1, round(width / f)), max(1, round(width / f))", ("tests/test_datasets_colmap.py",
             "tests/test_datasets_blender_ngp.py", "tests/test_datasets_sanity_detect.py", "tests/test_cli_own_scene.py"),
             "working height from the width"),
    Mutation("m57", "controlgs_adapter/datasets/base.py", "if h % height == 0 and w % width == 0 and h // height == w // width:",
             "if h % height == 0 and w % width == 0:", ("tests/test_datasets_colmap.py", "tests/test_datasets_blender_ngp.py"),
             "integer box downscale taken with unequal factors"),
    # --- a fourth sample (session F): family backends and loaders, file formats, rendering, camera, datasets, lock,
    # viewer state, training schedule and resume, evaluation axes
    Mutation("m58", "backends/octree_gs.py", "pos = pos + (self.voxel_size / 2) / (float(self.fork) ** self._level)",
             "pos = pos + self.voxel_size / (float(self.fork) ** self._level)", ("tests/test_backend_octree_gs.py",),
             "Octree LOD distance from the voxel's far corner, not its centre"),
    Mutation("m59", "backends/octree_gs.py", 'rnd = {"round": torch.round, "floor": torch.floor, "ceil": torch.ceil}',
             'rnd = {"round": torch.round, "floor": torch.ceil, "ceil": torch.floor}', ("tests/test_backend_octree_gs.py",),
             "Octree dist2level floor and ceil swapped"),
    Mutation("m60", "backends/octree_gs.py", "with_dist = torch.cat([feat, view, dist, *extra], dim=1)",
             "with_dist = torch.cat([feat, view, *extra, dist], dim=1)", ("tests/test_backend_octree_gs.py",),
             "Octree decoder input: level before the distance"),
    Mutation("m61", "backends/octree_gs.py", "return _build(t, folder, trust_code, f\"{folder} + {cfg_path}\", voxel_size=float(info[0]),\n                  standard_dist=float(info[1]),",
             "return _build(t, folder, trust_code, f\"{folder} + {cfg_path}\", voxel_size=float(info[1]),\n                  standard_dist=float(info[0]),",
             ("tests/test_backend_octree_gs.py", "tests/test_model_dir.py"), "Octree-GS loader: info rows 0 and 1 swapped"),
    Mutation("m62", "backends/hac.py", "return m if self.decoded_version else (torch.sigmoid(m) > _MASK_THRESHOLD).to(m.dtype)",
             "return m if self.decoded_version else (m > _MASK_THRESHOLD).to(m.dtype)",
             ("tests/test_backend_hac.py", "tests/test_backend_contextgs.py"), "raw HAC mask logits thresholded without the sigmoid"),
    Mutation("m63", "backends/hac.py", "m = self._mask[:, : self.n_offsets]", "m = self._mask[:, -self.n_offsets:]",
             ("tests/test_backend_hac.py", "tests/test_backend_contextgs.py"), "HAC++ offset masks read from the last K columns"),
    Mutation("m64", "backends/hac.py", "keep = (opacity > 0) & (self.get_mask[ids].reshape(-1) > 0)", "keep = opacity > 0",
             ("tests/test_backend_hac.py", "tests/test_backend_contextgs.py"), "HAC decode keeps masked-off offsets"),
    Mutation("m65", "backends/hac.py", "model.source_index = model.source_index[keep].clone()",
             "model.source_index = model.source_index[: int(keep.sum())].clone()",
             ("tests/test_backend_hac.py", "tests/test_backend_contextgs.py", "tests/test_adapter_io.py"),
             "dropping invalid anchors keeps the first source rows, not the kept ones"),
    Mutation("m66", "backends/compgs.py", "view = torch.cat([vec / dist, dist], dim=1).repeat_interleave(k, dim=0)",
             "view = torch.cat([vec / dist, dist], dim=1).repeat(k, 1)", ("tests/test_backend_compgs.py",),
             "CompGS view/dist rows tiled instead of grouped per anchor"),
    Mutation("m67", "backends/compgs.py", "res_feats=torch.from_numpy(np.ascontiguousarray(res_flat.reshape(-1, k, g))),",
             "res_feats=torch.from_numpy(np.ascontiguousarray(res_flat.reshape(-1, g, k).transpose(0, 2, 1))),",
             ("tests/test_backend_compgs.py", "tests/test_model_dir.py"), "CompGS f_res_feat_* read g-major, not k-major"),
    Mutation("m68", "backends/contextgs.py", "    return q * step + lo", "    return (q + 0.5) * step + lo",
             ("tests/test_backend_contextgs.py",), "ContextGS dequantised anchor at the bin centre"),
    Mutation("m69", "backends/contextgs.py", "step = (hi - lo) * (1.0 / levels) + 1e-6", "step = (hi - lo) * (1.0 / levels)",
             ("tests/test_backend_contextgs.py",), "ContextGS quantisation step without its 1e-6"),
    Mutation("m70", "backends/scaffold_io.py", "add_cov_dist=model.add_cov_dist,", "add_cov_dist=model.add_opacity_dist,",
             ("tests/test_scaffold_io.py", "tests/test_reference_model.py"), "cfg_args records add_cov_dist from add_opacity_dist"),
    Mutation("m71", "backends/model_dir.py", "model = load_hac_dir(path, iteration, allow_unquantized=allow_unquantized)",
             "model = load_hac_dir(path, None, allow_unquantized=allow_unquantized)",
             ("tests/test_model_dir.py", "tests/test_backend_hac.py"), "load_model_dir ignores the iteration for HAC"),
    Mutation("m72", "controlgs_adapter/formats/layout.py", "        return found[max(found)]\n", "        return found[min(found)]\n",
             ("tests/test_scaffold_io.py", "tests/test_model_dir.py", "tests/test_backend_hac.py", "tests/test_formats.py"),
             "iteration None takes the lowest iteration"),
    Mutation("m73", "controlgs_adapter/formats/decoders.py", '"mlp_opacity": {1: nn.ReLU, 3: nn.Tanh}',
             '"mlp_opacity": {1: nn.ReLU, 3: nn.Sigmoid}',
             ("tests/test_backend_hac.py", "tests/test_backend_contextgs.py", "tests/test_scaffold_io.py"),
             "state-dict opacity decoders rebuilt with a sigmoid"),
    Mutation("m74", "controlgs_adapter/formats/decoders.py", "3: functools.partial(nn.Softmax, dim=1)",
             "3: functools.partial(nn.Softmax, dim=0)",
             ("tests/test_backend_hac.py", "tests/test_scaffold_io.py", "tests/test_backend_octree_gs.py"),
             "feature-bank softmax over rows, not over its 3 weights"),
    Mutation("m75", "controlgs_adapter/formats/adapter.py", 'isinstance(s.get(k), (int, float)) for k in ("lo", "hi")',
             'isinstance(s.get(k), (int, float)) for k in ("lo",)', ("tests/test_adapter_io.py", "tests/test_bad_inputs.py"),
             "adapter header check lets a schedule without 'hi' through"),
    Mutation("m76", "controlgs_adapter/formats/safetensors.py", "if isinstance(v, bool) or not isinstance(v, int) or v < 1:",
             "if isinstance(v, bool) or not isinstance(v, int) or v < 0:",
             ("tests/test_adapter_io.py", "tests/test_bad_inputs.py", "tests/test_formats.py"), "format_version 0 accepted"),
    Mutation("m77", "controlgs_adapter/formats/safetensors.py", "if pid.isdigit() and int(pid) != os.getpid() and not _pid_alive(int(pid)):",
             "if pid.isdigit() and int(pid) != os.getpid():", ("tests/test_bad_inputs.py", "tests/test_formats.py"),
             "a write removes the temporary files of live writers"),
    Mutation("m78", "controlgs_adapter/formats/checkpoint.py", '_FREE_CONFIG = ("iterations", "checkpoint_every")',
             '_FREE_CONFIG = ("iterations", "checkpoint_every", "lr")', ("tests/test_checkpoint_format.py", "tests/test_training.py"),
             "resume accepts a checkpoint trained with another learning rate"),
    Mutation("m79", "controlgs_adapter/controlgs.py", "if problems and (strict or any(s == \"fatal\" for _, s in problems)):",
             "if problems and strict:", ("tests/test_adapter_io.py", "tests/test_adapter_names.py", "tests/test_controlgs.py"),
             "non-strict load goes on past a fatal mismatch"),
    Mutation("m80", "controlgs_adapter/controlgs.py", "skipped = [m for m, s in problems if s is not None]",
             "skipped = [m for m, s in problems]", ("tests/test_adapter_io.py", "tests/test_adapter_names.py"),
             "reported-only mismatches listed as skipped"),
    Mutation("m81", "controlgs_adapter/rendering/rasterizers.py",
             "opacities = opacities - (opacities - opacities.clamp(max=ALPHA_MAX)).detach()",
             "opacities = opacities.clamp(max=ALPHA_MAX)", ("tests/test_rasterizers.py",),
             "gsplat < 1.6 opacity cap without the straight-through gradient"),
    Mutation("m82", "controlgs_adapter/state.py", "2.0 * math.atan(self.height / (2.0 * float(k[1, 1])))",
             "2.0 * math.atan(self.height / (2.0 * float(k[0, 0])))", ("tests/test_state.py", "tests/test_camera_scaffold.py"),
             "vertical field of view from fx"),
    Mutation("m83", "controlgs_adapter/datasets/instant_ngp.py", "src = entry if any(k in entry for k in keys) else meta",
             "src = entry if all(k in entry for k in keys) else meta", ("tests/test_datasets_blender_ngp.py",),
             "instant-ngp per-frame keys used only when the frame has the whole group"),
    Mutation("m84", "controlgs_adapter/datasets/instant_ngp.py", 'fy = p["fl_y"] if "fl_y" in p else _focal(where, p.get("camera_angle_y"), h, "y")',
             'fy = p["fl_y"] if "fl_y" in p else _focal(where, p.get("camera_angle_y"), w, "y")',
             ("tests/test_datasets_blender_ngp.py",), "instant-ngp fy from camera_angle_y and the width"),
    Mutation("m85", "controlgs_adapter/datasets/instant_ngp.py", "distortion = (d[0], d[1], d[2], d[3], d[4]) if any(d) else None",
             "distortion = (d[0], d[1], d[3], d[2], d[4]) if any(d) else None", ("tests/test_datasets_blender_ngp.py",),
             "instant-ngp p1, p2 swapped"),
    Mutation("m86", "controlgs_adapter/datasets/detect.py", "return read_instant_ngp(root, holdout=holdout, background=bg)",
             "return read_instant_ngp(root, background=bg)", ("tests/test_datasets_sanity_detect.py", "tests/test_datasets_blender_ngp.py"),
             "load_dataset drops holdout for instant-ngp"),
    Mutation("m87", "controlgs_adapter/lock.py", "fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)",
             "fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)", ("tests/test_bad_inputs.py",), "run lock taken shared"),
    Mutation("m88", "controlgs_adapter/viewer/session.py", 'check_number("gaze y", gaze[1], low=-1, high=1))',
             'check_number("gaze y", gaze[0], low=-1, high=1))', ("tests/test_viewer.py",), "viewer gaze y read from x"),
    Mutation("m89", "controlgs_adapter/viewer/session.py", 'view = check_number("view", data.get("view", d.view), integer=True, low=0, high=views - 1)',
             'view = check_number("view", data.get("view", d.view), integer=True, low=0, high=views)', ("tests/test_viewer.py",),
             "viewer accepts view == number of views"),
    Mutation("m90", "controlgs_adapter/training.py", 'return "distortion" if iteration < switch else self.config.psf_mode',
             'return "distortion" if iteration <= switch else self.config.psf_mode',
             ("tests/test_training.py", "tests/test_evaluation_optics_mode.py"), "PSF phase starts one iteration late"),
    Mutation("m91", "controlgs_adapter/training.py", "        self.generator.set_state(saved.rng)\n", "",
             ("tests/test_training.py", "tests/test_checkpoint_format.py"), "resume does not restore the sampling RNG"),
    Mutation("m92", "controlgs_adapter/evaluation.py",
             'renders["no_ss"] = render_view(None, model, cam.scaled(d), None, background, renderer=renderer)',
             'renders["no_ss"] = render_view(None, model, cam, None, background, renderer=renderer)',
             ("tests/test_report_honest.py", "tests/test_public_api.py", "tests/test_demo.py", "tests/test_evaluation_optics_mode.py"),
             "no-SS baseline rendered at the native size"),
    # --- a fifth sample (m93-m120) at sites no batch sampled: shared decode pieces, family inputs, schedules,
    # placement, metrics, colour, lens, resampling, injector, evaluation, report, datasets, camera, checks
    Mutation("m93", "backends/models/anchor_model.py", "feat[:, ::2].repeat(1, 2) * weight[:, 1:2]",
             "feat[:, ::2].repeat(1, 2) * weight[:, :1]", FAMILY_TESTS, "feature bank: half-resolution channels take the first weight"),
    Mutation("m94", "backends/models/anchor_model.py", "radius = torch.ceil(3.0 * torch.sqrt(",
             "radius = torch.ceil(2.0 * torch.sqrt(", FAMILY_TESTS, "anchor prefilter radius 2 sigma instead of 3"),
    Mutation("m95", "backends/octree_gs.py", "bank_in = torch.cat([view, level], dim=1) if self.add_level else view",
             "bank_in = torch.cat([view, dist], dim=1) if self.add_level else view", FAMILY_TESTS,
             "Octree-GS feature bank fed the distance instead of the level"),
    # (m96 first drew the LOD voxel-centre offset, m58's site; replaced by the level count)
    Mutation("m96", "backends/octree_gs.py", "int(level.max() - level.min() + 1) if n else 1",
             "int(level.max() - level.min()) if n else 1", FAMILY_TESTS,
             "Octree-GS level count without levels= one short (top level never selected)"),
    Mutation("m97", "backends/octree_gs.py", 'appearance_id = int(camera.extra.get("uid", 0))', "appearance_id = 0",
             FAMILY_TESTS, "Octree-GS appearance code ignores the camera's uid"),
    Mutation("m98", "backends/models/reference_model.py", "color_in = with_dist if self.add_color_dist else without_dist",
             "color_in = with_dist if self.add_opacity_dist else without_dist",
             ("tests/test_by_hand_decodes.py", "tests/test_reference_model.py", "tests/test_scaffold_io.py"),
             "Scaffold-GS colour input follows add_opacity_dist"),
    Mutation("m99", "backends/compgs.py", "return self.tail_activation(self.net(x) + self.skip(x))",
             "return self.tail_activation(self.net(x))", FAMILY_TESTS, "CompGS ResidualMLP without its skip path"),
    Mutation("m100", "backends/compgs.py", "torch.exp(p.scales_before_exp[:, :3]), p.rotations_before_norm)",
             "torch.exp(p.scales_before_exp[:, 3:]), p.rotations_before_norm)", FAMILY_TESTS,
             "CompGS prefilter with the base scales instead of the offset scales"),
    Mutation("m101", "controlgs_adapter/schedules.py", "torch.linalg.vector_norm(screen_xy - gaze, dim=-1)",
             "torch.linalg.vector_norm(screen_xy + gaze, dim=-1)", ("tests/test_schedules.py", "tests/test_options_by_hand.py",
                                                                    "tests/test_regressions.py"), "foveation eccentricity |p + gaze|"),
    Mutation("m102", "controlgs_adapter/schedules.py", "self.hi if hi is None else hi)", "self.hi if hi is None else lo)",
             ("tests/test_schedules.py", "tests/test_options_by_hand.py", "tests/test_adapter_io.py"),
             "with_endpoints: hi taken from lo"),
    Mutation("m103", "downstream/placement.py", "ImageRegion(1.0, 1.0, (dw / width, dh / height), (dw, dh), (dw, dh))",
             "ImageRegion(1.0, 1.0, (dw / width, dh / width), (dw, dh), (dw, dh))", PLACEMENT_TESTS,
             "'stretch' pitch: y from the width"),
    Mutation("m104", "downstream/placement.py", "(p, p), (width * p, dh), (dw, dh))", "(p, p), (height * p, dh), (dw, dh))",
             PLACEMENT_TESTS, "height-limited 'fit': region width from the height"),
    Mutation("m105", "controlgs_adapter/metrics.py", "g = torch.exp(-(r**2) / (2.0 * sigma**2))",
             "g = torch.exp(-(r**2) / (2.0 * sigma))", ("tests/test_metrics.py", "tests/test_options_by_hand.py"),
             "SSIM window: sigma not squared"),
    Mutation("m106", "controlgs_adapter/losses.py", "loss = loss + weights.ssim * (1.0 - ssim(",
             "loss = loss + weights.l1 * (1.0 - ssim(", ("tests/test_metrics.py", "tests/test_options_by_hand.py",
                                                          "tests/test_training.py"), "loss SSIM term weighted by the L1 weight"),
    Mutation("m107", "downstream/color.py", "to_primaries = raw / white[:, None]", "to_primaries = raw / white[None, :]",
             ("tests/test_stages_color.py", "tests/test_stages_lens.py", "tests/test_pipeline.py"),
             "primaries matrix normalised per column, not per row"),
    Mutation("m108", "downstream/display.py", "WATTS_PER_UNIT: float = 3.0 / 1000.0", "WATTS_PER_UNIT: float = 3.0 / 100.0",
             ("tests/test_stages_display.py", "tests/test_regressions.py", "tests/test_display_mapping.py"),
             "display power in watts off by 10"),
    Mutation("m109", "downstream/lens.py", "return -1.0 + 1.0 / n, 1.0 - 1.0 / n", "return -1.0 + 0.5 / n, 1.0 - 0.5 / n",
             ("tests/test_stages_lens.py", "tests/test_lens_optics_checks.py", "tests/test_display_mapping.py"),
             "LUT cell centres half a cell off"),
    Mutation("m110", "downstream/lens.py", "x0 = fx.detach().floor().clamp(0, gw - 2).long()",
             "x0 = fx.detach().round().clamp(0, gw - 2).long()",
             ("tests/test_stages_lens.py", "tests/test_lens_optics_checks.py", "tests/test_display_mapping.py"),
             "LUT bilinear lookup: left sample rounded, not floored"),
    Mutation("m111", "downstream/resample.py", "taps = int(math.ceil(n_in / n_out)) + 1", "taps = int(math.ceil(n_in / n_out))",
             ("tests/test_stages_resample.py", "tests/test_pipeline.py"), "area filter one tap short"),
    Mutation("m112", "downstream/resample.py", "if h % size[0] == 0 and w % size[1] == 0 and h // size[0] == w // size[1]:",
             "if h % size[0] == 0 and w % size[1] == 0:", ("tests/test_stages_resample.py", "tests/test_pipeline.py"),
             "area resample fast path taken with unequal factors"),
    Mutation("m113", "controlgs_adapter/injector.py", "return int(self.anchor_ids.shape[0]) * self.rows_per_anchor",
             "return int(self.anchor_ids.shape[0])", ("tests/test_controlgs.py", "tests/test_backend_compgs.py",
                                                       "tests/test_regressions.py"), "injection rows ignore rows per anchor"),
    Mutation("m114", "controlgs_adapter/evaluation.py", "eye = pipeline(rendered, state, reference=gt).clamp(0.0, 1.0)",
             "eye = pipeline(rendered, state, reference=None).clamp(0.0, 1.0)",
             ("tests/test_report_honest.py", "tests/test_demo.py", "tests/test_evaluation_optics_mode.py",
              "tests/test_prewarp_fidelity.py"), "evaluation's display stage without the ground truth's power"),
    Mutation("m115", "controlgs_adapter/report.py", 'summary[b][k]["std"] ** 2) / 2.0)', 'summary[b][k]["std"] ** 2))',
             ("tests/test_report_honest.py", "tests/test_findings_by_hand.py", "tests/test_demo.py"), "pooled spread without the / 2"),
    Mutation("m116", "controlgs_adapter/report.py", "wins = int((delta > 0).sum())", "wins = int((delta >= 0).sum())",
             ("tests/test_report_honest.py", "tests/test_findings_by_hand.py", "tests/test_demo.py"), "ties counted as wins"),
    Mutation("m117", "controlgs_adapter/datasets/images.py", "background.to(img).view(3, 1, 1) * (1.0 - a)",
             "background.to(img).view(3, 1, 1) * a", DATASET_TESTS, "RGBA background weighted by alpha"),
    Mutation("m118", "controlgs_adapter/datasets/images.py", "(fy * d[..., 1] + cy) * (2.0 / h) - 1.0",
             "(fy * d[..., 1] + cy) * (2.0 / w) - 1.0", DATASET_TESTS, "undistort grid y normalised by the width"),
    Mutation("m119", "controlgs_adapter/datasets/base.py", "f = max(1.0, max(width, height) / resolution)",
             "f = max(1.0, min(width, height) / resolution)", DATASET_TESTS, "--resolution N applied to the shorter side"),
    Mutation("m120", "controlgs_adapter/datasets/blender.py", "w2c[:3, 3] = -r.T @ t", "w2c[:3, 3] = -t", DATASET_TESTS,
             "Blender world-to-camera translation not rotated"),
    Mutation("m121", "controlgs_adapter/rendering/rasterizers.py", "int(m.group(2))) >= (1, 6) else 0.999",
             "int(m.group(2))) > (1, 6) else 0.999", ("tests/test_rasterizers.py",), "gsplat 1.6 given the old alpha cap"),
    Mutation("m122", "controlgs_adapter/state.py", "return -(r.transpose(0, 1) @ t)", "return -(r @ t)",
             ("tests/test_state.py", "tests/test_camera_scaffold.py", "tests/test_by_hand_decodes.py"),
             "camera centre without the transposed rotation"),
    Mutation("m123", "controlgs_adapter/state.py", "return points @ w2c[:3, :3].transpose(0, 1) + w2c[:3, 3]",
             "return points @ w2c[:3, :3] + w2c[:3, 3]", ("tests/test_state.py", "tests/test_camera_scaffold.py",
                                                          "tests/test_by_hand_decodes.py"), "to_camera with R^T"),
    Mutation("m124", "controlgs_adapter/training.py", "rho = float(u[1]) * c.max_power_saving", "rho = float(u[1]) * 0.8",
             ("tests/test_training.py", "tests/test_options_by_hand.py"), "power saving sampled up to 0.8 whatever the config"),
    Mutation("m125", "controlgs_adapter/checks.py", "(v > low if low_open else v >= low)", "(v >= low if low_open else v >= low)",
             ("tests/test_bad_inputs.py", "tests/test_training.py", "tests/test_state.py"), "open lower bound accepts the bound"),
)



def _run(worktree: Path, m: Mutation, timeout: float) -> tuple[bool, float, str]:
    """Apply ``m`` in ``worktree``, run its tests, restore; (caught, seconds, last line)."""
    target = worktree / m.path
    original = target.read_text()
    if original.count(m.old) != 1:
        raise SystemExit(f"{m.id}: the original text occurs {original.count(m.old)} times in {m.path}")
    target.write_text(original.replace(m.old, m.new))
    boot = ("import sys, pytest, __editable___controlgs_adapter_0_1_0_finder as f; "
            f"f.MAPPING.update({{'controlgs_adapter': {str(worktree / 'controlgs_adapter')!r}, "
            f"'controlgs_adapter.backends': {str(worktree / 'backends')!r}, "
            f"'controlgs_adapter.downstream': {str(worktree / 'downstream')!r}}}); "
            "sys.exit(pytest.main(sys.argv[1:]))")
    start = time.perf_counter()
    try:
        proc = subprocess.run([sys.executable, "-c", boot, "-x", "-q", "-rf", "-p", "no:cacheprovider", *m.tests],
                              cwd=worktree, capture_output=True, text=True, timeout=timeout)
        failed = [ln.split(" ")[1] for ln in proc.stdout.splitlines() if ln.startswith("FAILED ")]
        caught, tail = proc.returncode != 0, (failed or proc.stdout.strip().splitlines() or [""])[-1]
    except subprocess.TimeoutExpired:
        caught, tail = True, "timeout"
    finally:
        target.write_text(original)
    return caught, time.perf_counter() - start, tail


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", help="mutation ids to run (default: all)")
    ap.add_argument("--worktree", default="/tmp/mut")
    ap.add_argument("--timeout", type=float, default=600.0)
    args = ap.parse_args()
    chosen = [m for m in MUTATIONS if not args.only or m.id in args.only]
    worktree = Path(args.worktree)
    subprocess.run(["git", "worktree", "add", "--detach", str(worktree), "HEAD"], cwd=ROOT, check=True,
                   capture_output=True)
    try:
        bad = [f"{m.id} ({m.path}: {(worktree / m.path).read_text().count(m.old)}x)" for m in chosen
               if (worktree / m.path).read_text().count(m.old) != 1]
        if bad:
            raise SystemExit(f"the original text must occur once: {', '.join(bad)}")
        results = []
        for m in chosen:
            caught, secs, tail = _run(worktree, m, args.timeout)
            results.append((m, caught))
            print(f"{m.id:4s} {'caught' if caught else 'MISSED':6s} {secs:6.1f}s  {m.what}  [{tail}]", flush=True)
        n = sum(c for _, c in results)
        others = [c for m, c in results if not m.id.startswith("i")]
        print(f"caught {n}/{len(results)}; other sites {sum(others)}/{len(others)}")
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(worktree)], cwd=ROOT, check=False)


if __name__ == "__main__":
    main()
