"""The training checkpoint: one safetensors file holding what resuming a run needs.

Tensors: the adapter's state dict as ``adapter.<key>``, Adam's per-parameter state as
``optimizer.<index>.<step|exp_avg|exp_avg_sq>`` and the sampling generator's state as ``rng``. The
JSON header (on top of the container's ``kind``, ``format_version``, ``library_version``):
``iteration``, ``config`` (:meth:`~controlgs_adapter.training.TrainConfig.as_header`),
``modules``, ``effects`` (the downstream stages that are on), ``fingerprint`` (the backbone's),
``data`` (the training views'), ``lens`` (the fingerprint of the PSF bank the run simulates; a file
without it was written before lenses were recorded and resumes under any), ``param_groups`` (Adam's, without tensors) and ``history`` (the
loss of every iteration). Written atomically (:mod:`controlgs_adapter.formats.safetensors`).
:meth:`Trainer.save_checkpoint <controlgs_adapter.training.Trainer.save_checkpoint>` and
:meth:`~controlgs_adapter.training.Trainer.load_checkpoint` are the API; this module only
converts between the file and :class:`Checkpoint`, checking a file against the run that resumes it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import torch

from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.formats.safetensors import load_tensors, save_tensors

__all__ = ["CHECKPOINT_KIND", "CHECKPOINT_FORMAT_VERSION", "ADAM_STATE", "Checkpoint", "write_checkpoint",
           "read_checkpoint"]

CHECKPOINT_KIND = "controlgs_training_checkpoint"
CHECKPOINT_FORMAT_VERSION = 1
#: the per-parameter state of ``torch.optim.Adam``
ADAM_STATE = ("step", "exp_avg", "exp_avg_sq")
# config fields a resumed run may change: how long it trains and how often it checkpoints
_FREE_CONFIG = ("iterations", "checkpoint_every")


@dataclass
class Checkpoint:
    """The state of a training run, as a checkpoint file holds it.

    Attributes:
        adapter: the injector's state dict (conditions ``[A, M, N]``, projections ``[d1, N]``).
        optimizer_state: Adam's state by parameter index: ``{i: {"step", "exp_avg", "exp_avg_sq"}}``.
        param_groups: Adam's ``param_groups`` (hyper-parameters and parameter indices).
        rng: the sampling generator's state (``torch.Generator.get_state()``, uint8).
        iteration: steps done.
        history: the loss of every step so far.
        config: the :class:`~controlgs_adapter.training.TrainConfig` header.
        modules: the condition modules trained.
        effects: names of the downstream stages that are on, sorted.
        fingerprint: the backbone's fingerprint.
        data: the training views' fingerprint.
        lens: the fingerprint of the PSF bank of the lens the run simulates (None: no bank).
    """

    adapter: dict[str, torch.Tensor]
    optimizer_state: dict[int, dict[str, Any]]
    param_groups: list[dict[str, Any]]
    rng: torch.Tensor
    iteration: int
    history: list[float]
    config: dict[str, Any]
    modules: list[str]
    effects: list[str]
    fingerprint: str
    data: str
    lens: str | None = None

    def header(self) -> dict[str, Any]:
        """The JSON header of the file (without the container's fields)."""
        return {"iteration": self.iteration, "config": self.config, "modules": self.modules, "effects": self.effects,
                "fingerprint": self.fingerprint, "data": self.data, "lens": self.lens, "param_groups": self.param_groups,
                "history": self.history}

    def tensors(self) -> dict[str, torch.Tensor]:
        """The file's tensors, named as the module docstring says (a number in Adam's state becomes a 0-d tensor)."""
        tensors = {f"adapter.{k}": v for k, v in self.adapter.items()}
        for i, st in self.optimizer_state.items():
            for k, v in st.items():
                tensors[f"optimizer.{i}.{k}"] = v if isinstance(v, torch.Tensor) else torch.tensor(v)
        tensors["rng"] = self.rng
        return tensors


def write_checkpoint(path: str | Path, checkpoint: Checkpoint) -> Path:
    """Write ``checkpoint`` to ``path`` atomically; NaN/Inf anywhere is refused before writing."""
    return save_tensors(path, checkpoint.tensors(), checkpoint.header(), kind=CHECKPOINT_KIND,
                        format_version=CHECKPOINT_FORMAT_VERSION)


def read_checkpoint(path: str | Path, like: Checkpoint, param_shapes: Sequence[torch.Size]) -> Checkpoint:
    """Read the checkpoint at ``path`` for the run whose current state is ``like``, whose optimizer's
    parameters have ``param_shapes`` (in Adam's order).

    Checked, naming the file and what differs (:class:`FileFormatError`): the config (but for
    iterations and checkpoint_every), effects, backbone and data fingerprints and modules agree with
    ``like``; the adapter tensors are ``like``'s keys and shapes; Adam's state, ``param_groups`` and
    ``rng`` fit; ``iteration`` and ``history`` are well-formed; no tensor holds NaN/Inf.
    """
    tensors, header = load_tensors(path, kind=CHECKPOINT_KIND, max_version=CHECKPOINT_FORMAT_VERSION)
    _check_run(path, header, like)
    adapter, state = _split_tensors(path, tensors, like.adapter, param_shapes)
    iteration, history, groups = header.get("iteration"), header.get("history", []), header.get("param_groups")
    if isinstance(iteration, bool) or not isinstance(iteration, int) or iteration < 0:
        raise FileFormatError(f"{path}: checkpoint header field 'iteration' must be an integer >= 0, got {iteration!r}")
    if not isinstance(history, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                and math.isfinite(v) for v in history):
        raise FileFormatError(f"{path}: checkpoint header field 'history' must be a list of finite losses")
    own = like.param_groups
    if not isinstance(groups, list) or len(groups) != len(own) or not all(
            isinstance(g, dict) and g.get("params") == o["params"] for g, o in zip(groups, own)):
        raise FileFormatError(f"{path}: checkpoint header field 'param_groups' does not describe this optimizer "
                              f"({len(own)} Adam group(s) over parameters {[o['params'] for o in own]}), got {str(groups)[:80]}")
    rng, want = tensors.get("rng"), like.rng
    if rng is None or rng.dtype != want.dtype or rng.shape != want.shape:
        raise FileFormatError(f"{path}: checkpoint tensor 'rng' must be a {want.dtype} tensor of shape "
                              f"{list(want.shape)}, got " + ("none" if rng is None else f"{rng.dtype} {list(rng.shape)}"))
    return Checkpoint(adapter=adapter, optimizer_state=state, param_groups=groups, rng=rng, iteration=iteration,
                      history=list(history), config=header["config"], modules=header["modules"],
                      effects=header["effects"], fingerprint=header["fingerprint"], data=header["data"],
                      lens=header.get("lens", like.lens))


def _check_run(path: str | Path, header: dict[str, Any], like: Checkpoint) -> None:
    """Refuse a checkpoint of another run: config, effects, backbone, views or modules differ."""
    theirs = header.get("config")
    if not isinstance(theirs, dict) or not isinstance(theirs.get("loss", {}), dict):
        raise FileFormatError(f"{path}: checkpoint header field 'config' must be an object with a 'loss' object, "
                              f"got {str(theirs)[:80]}")
    mine = like.config
    diffs = [k for k in mine if k not in _FREE_CONFIG and mine[k] != theirs.get(k)]
    if diffs:
        raise FileFormatError(f"{path}: checkpoint was written with a different config ({', '.join(diffs)})")
    if header.get("effects") != like.effects:
        raise FileFormatError(f"{path}: checkpoint was trained through the stages {header.get('effects')}, this trainer's "
                              f"are {like.effects}")
    if header.get("fingerprint") != like.fingerprint:
        raise FileFormatError(f"{path}: checkpoint belongs to another backbone (fingerprint differs)")
    if header.get("data") != like.data:
        raise FileFormatError(f"{path}: checkpoint was trained on other views (data {header.get('data')}), this "
                              f"trainer's views are {like.data}")
    if "lens" in header and header["lens"] != like.lens:
        raise FileFormatError(f"{path}: checkpoint was trained through another lens (PSF bank {header['lens']}), this "
                              f"trainer's is {like.lens}")
    if header.get("modules") != like.modules:
        raise FileFormatError(f"{path}: checkpoint trains modules {header.get('modules')}, this trainer {like.modules}")


def _split_tensors(path: str | Path, tensors: dict[str, torch.Tensor], own: dict[str, torch.Tensor],
                   param_shapes: Sequence[torch.Size]) -> tuple[dict[str, torch.Tensor], dict[int, dict[str, Any]]]:
    """Split a checkpoint's tensors into the adapter's state dict (keys and shapes of ``own``) and
    Adam's state, refusing NaN/Inf, missing, unexpected and mis-shaped tensors (naming the file and tensor)."""
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise FileFormatError(f"{path}: checkpoint tensor(s) {bad} hold NaN/Inf: refusing to resume from it")
    adapter = {k[len("adapter."):]: v for k, v in tensors.items() if k.startswith("adapter.")}
    wrong = sorted(set(own) ^ set(adapter)) + sorted(k for k in set(own) & set(adapter) if own[k].shape != adapter[k].shape)
    if wrong:
        raise FileFormatError(f"{path}: checkpoint adapter tensors do not fit this adapter (missing, unexpected or "
                              f"mis-shaped: {wrong})")
    state: dict[int, dict[str, Any]] = {}
    for k, v in tensors.items():
        if k.startswith("optimizer."):
            parts = k.split(".")  # anything but optimizer.<index>.<state> has != 3 parts: refused
            if len(parts) != 3 or not parts[1].isdigit() or int(parts[1]) >= len(param_shapes) or parts[2] not in (
                    ADAM_STATE) or (parts[2] != "step" and v.shape != param_shapes[int(parts[1])]):
                raise FileFormatError(f"{path}: checkpoint tensor {k!r} ({list(v.shape)}) is not Adam state of "
                                      f"this adapter's {len(param_shapes)} parameters")
            state.setdefault(int(parts[1]), {})[parts[2]] = v
    extra = sorted(k for k in tensors if not k.startswith(("adapter.", "optimizer.")) and k != "rng")
    if extra:
        raise FileFormatError(f"{path}: checkpoint holds unexpected tensors {extra}")
    return adapter, state
