"""Suite-wide settings."""

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def _one_intra_op_thread():
    """The suite's tensors are small: one intra-op thread avoids OpenMP overhead and contention
    on a 2-core machine (measured up to 70x faster under load). Restored afterwards."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(autouse=True)
def _process_group_count():
    """A process group that fails to form in this process (tests of refusals) still bumps torch's
    count of groups, which names the store keys of the next group; a later test whose ranks run in
    fresh child processes (count 0) would then wait forever on keys nobody writes. Restored after
    every test."""
    from torch.distributed import distributed_c10d

    count = distributed_c10d._world.group_count
    yield
    if not torch.distributed.is_initialized():
        distributed_c10d._world.group_count = count


@pytest.fixture()
def fresh_plugins(monkeypatch):
    """A plug-in manager built anew on first use, with the plug-in environment variables unset
    (installed plug-ins autoload, a broken one only warns), and dropped again after the test."""
    from controlgs_adapter import plugins

    monkeypatch.delenv("CONTROLGS_DISABLE_PLUGIN_AUTOLOAD", raising=False)
    monkeypatch.delenv("CONTROLGS_STRICT_PLUGINS", raising=False)
    plugins.reset_plugin_manager()
    yield
    plugins.reset_plugin_manager()


@pytest.fixture(scope="module")
def tiny():
    """The built-in AR scene at 16 px (4 views) and an untrained backbone whose colours match it: enough
    to exercise the trainer. Built under a fixed seed without touching the global generator, so the
    model does not depend on which tests ran before."""
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.scene import load_builtin_scene

    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=2)
    xyz, rgb = scene.points(0.25)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.35, color_fit_steps=20)
    return scene, model.eval()


@pytest.fixture(scope="module")
def tiny_adapter(tiny, tmp_path_factory):
    """``tiny``'s model, the tiny scene's first two training views and an adapter file with random (non-zero) conditions."""
    scene, model = tiny
    views = scene.data.views("train", first=2)
    from controlgs_adapter import ControlGS

    cgs = ControlGS.wrap(model, cond_dim=4)
    with torch.no_grad(), torch.random.fork_rng(devices=[]):
        torch.manual_seed(3)
        for p in cgs.trainable_parameters():
            p.add_(0.5 * torch.randn_like(p))
    path = cgs.save(tmp_path_factory.mktemp("adapter") / "a.controlgs.safetensors")
    cgs.unwrap()
    return model, views, path
