"""Backbone families (installed as ``controlgs_adapter.backends``). :func:`load_model_dir` loads a
trained output folder of any supported family (detected from its files)."""

from .model_dir import FAMILIES, detect_family, load_model_dir

__all__ = ["FAMILIES", "detect_family", "load_model_dir"]
