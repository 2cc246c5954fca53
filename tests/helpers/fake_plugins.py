"""Installed plug-ins faked without installing anything: distributions and entry points that the plug-in manager discovers."""

from __future__ import annotations

import importlib.metadata
import importlib.util

import controlgs_adapter
from controlgs_adapter import plugins


class _FakeEntryPoint:
    def __init__(self, name, target, group=plugins.ENTRY_POINT_GROUP):
        self.name, self.group, self._target = name, group, target

    def load(self):
        if isinstance(self._target, BaseException):
            raise self._target
        return self._target


class _FakeDistribution:
    def __init__(self, name, version, entry_points):
        self.metadata = {"name": name}
        self.version = version
        self.entry_points = entry_points


class _GoodPlugin:
    @controlgs_adapter.hookimpl
    def controlgs_register_stages(self):
        from controlgs_adapter.downstream.stage import Stage

        class Sharpen(Stage):
            name = "sharpen_test"

            def forward(self, image, state, ctx):
                return image

        return [Sharpen]


def _fake_distributions(monkeypatch, *dists):
    real = importlib.metadata.distributions
    monkeypatch.setattr(importlib.metadata, "distributions", lambda: [*real(), *dists])
