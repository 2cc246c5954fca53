"""Write controlgs-adapter safetensors files *without* the library's checks, to build damaged files."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

import torch
from safetensors.torch import save_file

from controlgs_adapter._version import __version__
from controlgs_adapter.formats.safetensors import HEADER_KEY


def write_raw(path: str | Path, tensors: Mapping[str, torch.Tensor], header: Mapping[str, Any], *, kind: str,
              format_version: Any = 1, raw_header: str | None = None) -> Path:
    """A file as :func:`controlgs_adapter.formats.safetensors.save_tensors` writes it, NaN/Inf and odd headers allowed."""
    full = {"kind": kind, "format_version": format_version, "library_version": __version__, **header}
    meta = {HEADER_KEY: raw_header if raw_header is not None else json.dumps(full, sort_keys=True), "format": "pt"}
    save_file({k: v.detach().contiguous().clone() for k, v in tensors.items()}, str(path), metadata=meta)
    return Path(path)
