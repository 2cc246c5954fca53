"""Downstream stages between the renderer and the eye (installed as ``controlgs_adapter.downstream``)."""

from .stage import Stage, StageContext

__all__ = ["Stage", "StageContext"]
