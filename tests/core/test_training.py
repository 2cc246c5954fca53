"""Trainer: training images are checked as they load."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter.datasets.memory import posed_images
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.training import TrainConfig, Trainer

EFFECTS = {"lens": False, "resample": True, "display": True, "oled": False, "optics": None}


class _CountingViews:
    """Views whose images are made on first read (a lazily loading dataset), counting the loads."""

    def __init__(self, views, bad: int, value: float) -> None:
        self.inner, self.bad, self.value, self.loads = views, bad, value, []
        self.background = views.background
        self.cameras = views.cameras

    def __len__(self) -> int:
        return len(self.inner)

    def __getitem__(self, i):
        self.loads.append(i)
        cam, img = self.inner[i]
        if i == self.bad:
            img = img.clone()
            img[1, 0, 0] = self.value
        return cam, img


def _trainer(model, views, **cfg):
    config = TrainConfig(**{"iterations": 4, "checkpoint_every": 0, "seed": 0, **cfg})
    return Trainer(model, views, config, effects=EFFECTS)


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_a_non_finite_image_is_refused_at_its_first_load_naming_the_view(tiny, value):
    scene, model = tiny
    base = scene.views("train")
    cams = [base[i][0] for i in range(len(base))]
    imgs = [base[i][1].clone() for i in range(len(base))]
    imgs[1][0, 2, 3] = value
    views = posed_images(imgs, cams, background=base.background, name="train")
    t = _trainer(model, views, iterations=50)
    try:
        t.load_view(0)  # a finite view passes
        with pytest.raises(InputValueError, match=r"view 1 \('train/0001'\): image holds 1 NaN/Inf"):
            t.load_view(1)
        with pytest.raises(InputValueError, match=r"view 1 \('train/0001'\)"):
            t.train(progress=False)  # stops at the first draw of view 1, before its loss is taken
        assert len(t.history) < 50 and all(math.isfinite(v) for v in t.history)
    finally:
        t.cgs.unwrap()


def test_lazily_loaded_views_are_checked_when_first_read_and_only_then(tiny):
    scene, model = tiny
    views = _CountingViews(scene.views("train"), bad=2, value=math.nan)
    t = _trainer(model, views)
    try:
        assert views.loads == []  # building the trainer loads no image
        t.load_view(0)
        t.load_view(0)
        assert views.loads == [0, 0]
        assert t._checked_views == {0}
        with pytest.raises(InputValueError, match=r"^view 2: image holds 1 NaN/Inf value\(s\)"):
            t.load_view(2)
        assert 2 not in t._checked_views  # refused again on the next read
        with pytest.raises(InputValueError, match=r"^view 2:"):
            t.load_view(2)
    finally:
        t.cgs.unwrap()


def test_finite_views_train_as_before(tiny):
    scene, model = tiny
    t = _trainer(model, scene.views("train"), iterations=2)
    try:
        t.train(progress=False)
        assert len(t.history) == 2 and all(math.isfinite(v) for v in t.history)
        assert t._checked_views and t._checked_views <= set(range(len(scene.views("train"))))
    finally:
        t.cgs.unwrap()


class _NanGradient(torch.autograd.Function):
    """Identity forward; a NaN gradient backward (a render whose backward breaks down at a finite loss)."""

    @staticmethod
    def forward(ctx, x):
        return x.clone()

    @staticmethod
    def backward(ctx, grad):
        return torch.full_like(grad, math.nan)


def test_nan_gradients_at_a_finite_loss_are_named_as_the_cause_not_the_learning_rate(tiny):
    from controlgs_adapter.errors import NonFiniteError
    from controlgs_adapter.rendering.protocol import FunctionRenderer

    scene, model = tiny

    def nan_backward(m, camera, visible, background):
        return _NanGradient.apply(m.render(camera, visible, background).color)

    config = TrainConfig(iterations=2, checkpoint_every=0, seed=0, lr=1e-3)
    t = Trainer(model, scene.views("train"), config, effects=EFFECTS,
                renderer=FunctionRenderer(nan_backward, visible=lambda m, c: m.visible_anchors(c)))
    try:
        with pytest.raises(NonFiniteError, match=r"training diverged at iteration 0: parameter\(s\) \[.+\] became NaN/Inf "
                                                 r"from NaN/Inf gradients of \['conditions'.*\] with a finite loss: not the "
                                                 r"learning rate") as e:
            t.step()
        assert "lr 0.001" not in str(e.value)
    finally:
        t.cgs.unwrap()


def test_a_model_with_a_degenerate_gaussian_trains(tiny):
    """One anchor's Gaussians with scales of about 1e20 (a float32 2D covariance would overflow): the steps
    keep every adapter tensor finite."""
    import copy

    scene, model = tiny
    model = copy.deepcopy(model)
    cam = scene.test_cameras[0]
    with torch.no_grad():
        g = model.decode(cam, model.visible_anchors(cam))
        model._scaling[int(g.anchor_of[g.opacities.argmax()]), 3:] = math.log(1e20)
    t = _trainer(model, scene.views("train"), iterations=3)
    try:
        t.train(progress=False)
        assert len(t.history) == 3 and all(math.isfinite(v) for v in t.history)
        assert all(bool(torch.isfinite(p).all()) for p in t.cgs.trainable_parameters())
    finally:
        t.cgs.unwrap()
