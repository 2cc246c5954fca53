"""Tests of ``controlgs_adapter.commands.adapters``."""

from __future__ import annotations

import pytest

from controlgs_adapter.commands.adapters import effects_from
from controlgs_adapter.errors import InputValueError


def test_effects_from_keeps_pipeline_order() -> None:
    from controlgs_adapter.training import DEFAULT_EFFECTS

    order = list(DEFAULT_EFFECTS)
    picked = [order[-1], order[0]]
    got = effects_from(f" {picked[0]} ,{picked[1]},")
    assert list(got) == [order[0], order[-1]] and all(v is True for v in got.values())
    assert effects_from(picked) == got
    assert effects_from(None) == dict(DEFAULT_EFFECTS)
    for bad in ("", " , ", f"{order[0]},bloom"):
        with pytest.raises(InputValueError, match="--effects must be a comma-separated list of"):
            effects_from(bad)


def test_effects_from_lists():
    from controlgs_adapter.commands.adapters import effects_from
    from controlgs_adapter.training import DEFAULT_EFFECTS

    assert effects_from(None) == dict(DEFAULT_EFFECTS) and effects_from(None) is not DEFAULT_EFFECTS
    names = list(DEFAULT_EFFECTS)
    assert effects_from([names[1], names[0]]) == {names[0]: True, names[1]: True}
    assert effects_from(f" {names[0]} ,, ") == {names[0]: True}
    for bad in ("", " , ", "nope", f"{names[0]},nope", []):
        with pytest.raises(InputValueError, match="--effects must be a comma-separated list of"):
            effects_from(bad)  # type: ignore[arg-type]
