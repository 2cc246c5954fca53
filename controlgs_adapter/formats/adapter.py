"""The adapter file: one safetensors file holding an adapter's tensors and a JSON header.

Building and checking the header, comparing a model's backbone fingerprint with the file's,
mapping saved condition rows onto a model's anchors, and reading / writing the tensors.
``ControlGS.save`` / ``ControlGS.load`` (:mod:`controlgs_adapter.controlgs`) are the public API;
the format is described in docs/reference/adapter-file-format.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from controlgs_adapter.backend import Backend
from controlgs_adapter.errors import FileFormatError, InputValueError, NonFiniteError
from controlgs_adapter.formats.safetensors import load_tensors, read_header, save_tensors
from controlgs_adapter.downstream.optics.visual_angles import VisualAngles
from controlgs_adapter.lens_frame import LensFrame

__all__ = ["ADAPTER_KIND", "ADAPTER_FORMAT_VERSION", "Problem", "AdapterSpec", "build_header", "check_header", "read_spec",
           "read_tensors", "write_adapter", "valid_fingerprint", "row_map", "map_conditions", "fingerprint_mismatch",
           "tensor_mismatches", "lens_frame_of", "visual_angles_of"]

ADAPTER_KIND = "controlgs_adapter"
#: the newest format: 2 adds the optional ``lens_frame`` field, 3 the optional ``visual_angles`` field; a file
#: is written in the oldest format that holds its fields (neither: format 1), which older readers read as meant
ADAPTER_FORMAT_VERSION = 3

# what a non-strict load leaves out for one mismatch: tensor keys, ("target", decoder), "conditions",
# None (only reported: the adapter still loads) or "fatal" (cannot be skipped)
Skip = frozenset[str] | tuple[str, str] | str | None
Problem = tuple[str, Skip]


@dataclass(frozen=True)
class AdapterSpec:
    """An adapter as plain data: what its file header records (:meth:`ControlGS.adapter_spec
    <controlgs_adapter.controlgs.ControlGS.adapter_spec>` gives it for the active adapter).

    Attributes:
        backend: the backend's name.
        modules: the condition modules, in order.
        cond_dim: N, size of each per-anchor condition.
        schedules: ``{module: {"class", "per_anchor", "lo", "hi"}}``.
        state_blind: the state-blind ablation (strength 1).
        targets: ``[{"decoder", "fc1", "in_features", "out_features"}]`` of the decoders it injects into.
        num_anchors, rows_per_anchor: the backbone's anchor count and decoder rows per anchor.
        fingerprint: the backbone's fingerprint; ``valid_fingerprint``: over its valid anchors only
            (None for backends without ``valid_anchors``, :func:`valid_fingerprint`).
        lens_frame: the lens condition's frame (:meth:`LensFrame.header
            <controlgs_adapter.lens_frame.LensFrame.header>`); None for a centred radius frame.
        visual_angles: the foveation module's visual-angle map (:meth:`VisualAngles.header
            <controlgs_adapter.downstream.optics.visual_angles.VisualAngles.header>`); None for the Cardboard lens's.
    """

    backend: str
    modules: list[str]
    cond_dim: int
    schedules: dict[str, dict[str, Any]]
    state_blind: bool
    targets: list[dict[str, Any]]
    num_anchors: int
    rows_per_anchor: int
    fingerprint: str
    valid_fingerprint: str | None = None
    lens_frame: dict[str, Any] | None = None
    visual_angles: dict[str, Any] | None = None


def build_header(spec: AdapterSpec) -> dict[str, Any]:
    """The JSON header of an adapter (without the fields io adds)."""
    return {
        "backend": spec.backend,
        "modules": list(spec.modules),
        "cond_dim": spec.cond_dim,
        "schedules": {m: dict(s) for m, s in spec.schedules.items()},
        "state_blind": spec.state_blind,
        "targets": [dict(t) for t in spec.targets],
        "num_anchors": spec.num_anchors,
        "rows_per_anchor": spec.rows_per_anchor,
        "fingerprint": spec.fingerprint,
        **({} if spec.valid_fingerprint is None else {"valid_fingerprint": spec.valid_fingerprint}),
        **({} if spec.lens_frame is None else {"lens_frame": spec.lens_frame}),
        **({} if spec.visual_angles is None else {"visual_angles": spec.visual_angles}),
    }


def write_adapter(path: str | Path, tensors: dict[str, torch.Tensor], header: dict[str, Any],
                  dtype: torch.dtype | None = None) -> Path:
    """Write an injector's ``tensors`` with ``header`` (atomically); ``dtype``: storage dtype of the
    conditions (None = as trained, or ``torch.float16``)."""
    if dtype not in (None, torch.float16, torch.float32):
        raise InputValueError(f"dtype must be None, torch.float16 or torch.float32, got {dtype!r}")
    peak = float(tensors["conditions"].abs().max()) if tensors["conditions"].numel() else 0.0
    if dtype == torch.float16 and peak > torch.finfo(torch.float16).max:
        raise NonFiniteError(f"{path}: conditions reach |{peak:.4g}|, beyond float16's range "
                             f"({torch.finfo(torch.float16).max:g}): save them as float32 (dtype=None)")
    if dtype is not None:
        tensors = {**tensors, "conditions": tensors["conditions"].to(dtype)}
    header = {**header, "condition_dtype": str(tensors["conditions"].dtype).removeprefix("torch.")}
    version = 3 if "visual_angles" in header else 2 if "lens_frame" in header else 1
    return save_tensors(path, tensors, header, kind=ADAPTER_KIND, format_version=version)


def read_spec(path: str | Path) -> dict[str, Any]:
    """The checked header of the adapter file at ``path`` (FileFormatError if unreadable or malformed)."""
    return check_header(path, read_header(path, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION))


def read_tensors(path: str | Path) -> dict[str, torch.Tensor]:
    """The tensors of the adapter file at ``path``."""
    return load_tensors(path, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION)[0]


_HEADER_FIELDS: dict[str, type | tuple[type, ...]] = {
    "backend": str, "modules": list, "cond_dim": int, "schedules": dict, "state_blind": bool, "targets": list,
    "num_anchors": int, "rows_per_anchor": int, "fingerprint": str,
}


def check_header(path: str | Path, header: dict[str, Any]) -> dict[str, Any]:
    """``header`` if every field has its type and each schedule's endpoints are finite and differ;
    else :class:`FileFormatError` naming ``path`` and the field(s)."""
    bad = [k for k, t in _HEADER_FIELDS.items() if not isinstance(header.get(k), t)]
    if not bad:
        for m in header["modules"]:
            s = header["schedules"].get(m)
            if not isinstance(s, dict) or not all(isinstance(s.get(k), (int, float)) for k in ("lo", "hi")):
                bad.append(f"schedules.{m}")
        for i, t in enumerate(header["targets"]):
            if not isinstance(t, dict) or not isinstance(t.get("decoder"), str) or not all(
                    isinstance(t.get(k), int) for k in ("in_features", "out_features")):
                bad.append(f"targets[{i}]")
    if bad:
        raise FileFormatError(f"{path}: adapter header is missing or has malformed field(s) {bad}")
    for m in header["modules"]:
        lo, hi = header["schedules"][m]["lo"], header["schedules"][m]["hi"]
        if not (math.isfinite(lo) and math.isfinite(hi)) or lo == hi:
            raise FileFormatError(f"{path}: adapter header field schedules.{m}: endpoints lo={lo!r}, hi={hi!r} must be "
                                  "finite and differ")
    lens_frame_of(path, header)
    visual_angles_of(path, header)
    return header


def lens_frame_of(path: str | Path, header: dict[str, Any]) -> LensFrame:
    """The lens frame the header records (none: a centred radius frame, as every format-1 file);
    :class:`FileFormatError` naming ``path`` and the field if it is malformed or does not fit the adapter
    (``"xy"`` needs the lens module and an even ``cond_dim``)."""
    if "lens_frame" not in header:
        return LensFrame()
    try:
        frame = LensFrame.from_header(header["lens_frame"])
    except InputValueError as e:
        raise FileFormatError(f"{path}: adapter header field {e}") from None
    if frame.mode == "xy" and ("lens" not in header["modules"] or header["cond_dim"] % 2):
        raise FileFormatError(f"{path}: adapter header field lens_frame.mode: 'xy' needs the 'lens' module and an "
                              f"even cond_dim, got modules {header['modules']} and cond_dim {header['cond_dim']}")
    return frame


def visual_angles_of(path: str | Path, header: dict[str, Any]) -> VisualAngles | None:
    """The foveation module's visual-angle map the header records (none: the Cardboard lens's, as every file
    before format 3); :class:`FileFormatError` naming ``path`` and the field if it is malformed or comes
    without the foveation module."""
    if "visual_angles" not in header:
        return None
    if "foveation" not in header["modules"]:
        raise FileFormatError(f"{path}: adapter header field visual_angles: only the 'foveation' module has one, got "
                              f"modules {header['modules']}")
    try:
        return VisualAngles.from_header(header["visual_angles"])
    except InputValueError as e:
        raise FileFormatError(f"{path}: adapter header field {e}") from None


def valid_fingerprint(model: Any, backend: Backend) -> str | None:
    """Fingerprint over the anchors that produce Gaussians, for backends that tell them
    (``valid_anchors``: HAC, ContextGS); None for the others."""
    valid = getattr(backend, "valid_anchors", None)
    if valid is None:
        return None
    return backend.fingerprint(model, valid(model).nonzero().squeeze(1))


def row_map(model: Any, backend: Backend, spec: dict[str, Any]) -> tuple[str, torch.Tensor] | None:
    """How the saved condition rows map onto ``model``'s anchors when the adapter was trained on the
    same scene with or without its invalid anchors (a live zero-padded HAC/ContextGS model vs the
    loaded stand-in, which drops them and keeps each anchor's file row in ``source_index``):
    ``("gather", rows)``: model anchor i takes saved row ``rows[i]``; ``("scatter", ids)``: saved
    row j goes to model anchor ``ids[j]`` (the others stay zero, inert). None: no mapping (the
    anchor counts agree, or nothing proves it is the same scene)."""
    want, a, saved = spec.get("valid_fingerprint"), backend.num_anchors(model), spec["num_anchors"]
    valid = getattr(backend, "valid_anchors", None)
    if not isinstance(want, str) or a == saved or valid is None:
        return None
    source = getattr(model, "source_index", None)
    if (isinstance(source, torch.Tensor) and source.shape == (a,) and a < saved and int(source.max()) < saved
            and valid_fingerprint(model, backend) == want and bool(valid(model).all())):
        return "gather", source.long()
    ids = valid(model).nonzero().squeeze(1)
    if ids.numel() == saved and backend.fingerprint(model, ids) == want:
        return "scatter", ids
    return None


def map_conditions(saved: torch.Tensor, rows: tuple[str, torch.Tensor], num_anchors: int) -> torch.Tensor:
    """The saved condition table mapped onto the model's ``num_anchors`` anchors by :func:`row_map`'s result."""
    kind, index = rows
    if kind == "gather":
        return saved.index_select(0, index.to(saved.device))
    full = saved.new_zeros((num_anchors, *saved.shape[1:]))
    full[index.to(saved.device)] = saved
    return full


def fingerprint_mismatch(spec: dict[str, Any], fingerprint: str) -> list[Problem]:
    """The backbone-fingerprint mismatch between the file and a model (reported only: a non-strict load goes on)."""
    if fingerprint == spec["fingerprint"]:
        return []
    return [(f"backbone fingerprint: the adapter was trained on backbone {spec['fingerprint']}, "
             f"this model is {fingerprint} (other anchors or decoder weights)", None)]


def tensor_mismatches(tensors: dict[str, torch.Tensor], spec: dict[str, Any]) -> list[Problem]:
    n, a = spec["cond_dim"], spec["num_anchors"]
    widths = sorted({t["out_features"] for t in spec["targets"]})
    expected: dict[str, tuple[int, ...]] = {"conditions": (a, len(spec["modules"]), n)}
    for m in spec["modules"]:
        for d1 in widths:
            expected[f"projections.{m}.d{d1}.weight"] = (d1, n)
    problems: list[Problem] = []
    missing = sorted(set(expected) - set(tensors))
    unexpected = sorted(set(tensors) - set(expected))
    if missing:
        problems.append((f"tensors missing from the file: {missing}", frozenset(missing)))
    if unexpected:
        problems.append((f"unexpected tensors in the file: {unexpected}", frozenset(unexpected)))
    for k in sorted(set(expected) & set(tensors)):
        v = tensors[k]
        if tuple(v.shape) != expected[k]:
            problems.append((f"tensor {k!r}: shape {list(v.shape)}, expected {list(expected[k])}", frozenset({k})))
        elif not v.is_floating_point():
            problems.append((f"tensor {k!r}: dtype {v.dtype}, expected a floating-point type", frozenset({k})))
        elif not bool(torch.isfinite(v).all()):
            problems.append((f"tensor {k!r}: contains NaN/Inf", frozenset({k})))
    return problems
