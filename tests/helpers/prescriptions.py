"""Lens prescriptions for the optics tests: the Cardboard prescription with fields replaced."""

from __future__ import annotations

from typing import Any

from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription


def cardboard_spec(**over: Any) -> dict[str, Any]:
    """A copy of the Cardboard prescription's spec (lists copied) with the fields ``over`` replaced."""
    spec = {k: (list(v) if isinstance(v, list) else v) for k, v in CARDBOARD.items()}
    spec.update(over)
    return spec


def lens(surfaces: list[Any], **over: Any) -> Prescription:
    """The Cardboard prescription with ``surfaces`` (and the fields ``over``) replaced."""
    return Prescription(cardboard_spec(surfaces=surfaces, **over))
