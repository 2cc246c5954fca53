"""Sweep 2 (files area): the documented defaults of the public functions of datasets/, formats/ and
scene/, each observed through the public API (the default call equals the call with the documented
value and differs from a call with another value), and the messages that name a default."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from _datasets_synth import marker_image, ring_poses, write_json, write_png
from controlgs_adapter.datasets import load_dataset
from controlgs_adapter.datasets.base import Frame, SceneData, working_size
from controlgs_adapter.datasets.blender import read_blender, resolve_background
from controlgs_adapter.datasets.images import distort_normalized, undistort_points
from controlgs_adapter.datasets.instant_ngp import read_instant_ngp
from controlgs_adapter.errors import FileFormatError, InputValueError, TargetError
from controlgs_adapter.formats.backbone import parse_cfg_args, write_ply
from controlgs_adapter.formats.safetensors import as_path
from controlgs_adapter.formats.torchscript import eager_from_script
from controlgs_adapter.scene.cameras import arc_cameras
from controlgs_adapter.state import Camera


# --------------------------------------------------------------------------- datasets
def _ngp(root, n=10, transforms="transforms.json"):
    poses = ring_poses(n, phase=0.1)
    frames = []
    for i in range(n):
        write_png(root / "images" / f"img_{i:02d}.png", marker_image(8, 6, [], rgba=False, fill=(10 * i, 0, 0)))
        frames.append({"file_path": f"images/img_{i:02d}.png", "transform_matrix": poses[i].tolist()})
    write_json(root / transforms, {"fl_x": 9.0, "fl_y": 9.0, "cx": 4.0, "cy": 3.0, "w": 8.0, "h": 6.0, "frames": frames})


def _test_names(data):
    return [f.name for f in data.splits["test"]]


def test_instant_ngp_default_holdout_is_8_and_default_transforms_file(tmp_path):
    _ngp(tmp_path)
    # 10 frames named img_00..img_09: every 8th by name from the first -> img_00 and img_08
    want = ["images/img_00.png", "images/img_08.png"]
    assert _test_names(read_instant_ngp(tmp_path)) == want
    assert _test_names(load_dataset(tmp_path)) == want
    assert _test_names(load_dataset(tmp_path, format="instant_ngp")) == want
    assert _test_names(read_instant_ngp(tmp_path, holdout=3)) == ["images/img_00.png", "images/img_03.png",
                                                                  "images/img_06.png", "images/img_09.png"]
    assert len(read_instant_ngp(tmp_path).splits["train"]) == 8
    # the transforms file's default name is transforms.json: another name is found only when given
    other = tmp_path / "other"
    _ngp(other, n=3, transforms="transforms_x.json")
    with pytest.raises(FileFormatError, match="transforms.json"):
        read_instant_ngp(other)
    assert len(read_instant_ngp(other, transforms="transforms_x.json", holdout=0).splits["train"]) == 3


def test_blender_and_resolve_background_default_black(tmp_path):
    torch.testing.assert_close(resolve_background(None), torch.zeros(3))
    torch.testing.assert_close(resolve_background(None, True), torch.ones(3))
    px = np.zeros((6, 8, 4), dtype=np.uint8)  # fully transparent: the image is the background
    write_png(tmp_path / "train" / "r_0.png", px)
    write_json(tmp_path / "transforms_train.json",
               {"camera_angle_x": 0.8, "frames": [{"file_path": "train/r_0", "transform_matrix": ring_poses(1)[0].tolist()}]})
    assert float(read_blender(tmp_path).views("train").image(0).abs().max()) == 0.0
    assert float(read_blender(tmp_path, white_background=True).views("train").image(0).min()) == 1.0


def test_working_size_defaults_keep_the_size():
    assert working_size(640, 480) == (640, 480)
    assert working_size(640, 480, resolution=320) == (320, 240)
    assert working_size(640, 480, factor=4) == (160, 120)


# --------------------------------------------------------------------------- formats
def test_as_path_default_names_path():
    with pytest.raises(InputValueError, match=r"^path must be a file path \(str or os.PathLike\), got 5$"):
        as_path(5)
    with pytest.raises(InputValueError, match=r"^out must be a file path .*got ''$"):
        as_path("", "out")


def test_parse_cfg_args_default_source_is_cfg_args():
    with pytest.raises(FileFormatError, match=r"^cfg_args: not a printed argparse Namespace"):
        parse_cfg_args("Namespace(a=")
    with pytest.raises(FileFormatError, match=r"^run/cfg: not a printed argparse Namespace"):
        parse_cfg_args("Namespace(a=", source="run/cfg")


def test_eager_from_script_default_name_is_decoder():
    with pytest.raises(TargetError, match=r"^decoder 'decoder': expected a TorchScript module, got Linear$"):
        eager_from_script(nn.Linear(2, 2))  # type: ignore[arg-type]
    with pytest.raises(TargetError, match=r"^decoder 'decoder': the TorchScript module holds no Linear layer$"):
        eager_from_script(torch.jit.script(nn.Sequential(nn.ReLU())))
    with pytest.raises(TargetError, match=r"^decoder 'mlp_color': "):
        eager_from_script(torch.jit.script(nn.Sequential(nn.ReLU())), "mlp_color")


def _header(path) -> list[str]:
    raw = path.read_bytes()
    return raw[:raw.index(b"end_header\n")].decode("ascii").splitlines()


def test_write_ply_default_comments_none_and_keyword_comment(tmp_path):
    fields = {"x": np.arange(3, dtype=np.float32)}
    plain = _header(write_ply(tmp_path / "a.ply", fields))
    assert plain == ["ply", "format binary_little_endian 1.0", "element vertex 3", "property float x"]
    noted = _header(write_ply(tmp_path / "b.ply", fields, ["made by hand"]))
    assert noted[2] == "comment made by hand" and len(noted) == 5
    other = _header(write_ply(tmp_path / "c.ply", fields, ["x"], comment_keyword="obj_info"))
    assert other[2] == "obj_info x"


# --------------------------------------------------------------------------- scene
def test_arc_cameras_defaults_are_the_documented_numbers():
    default = arc_cameras(5, size=16)
    explicit = arc_cameras(5, size=16, fov_deg=50.0, radius=(4.2, 5.2), azimuth_deg=32.0, elevation_deg=(8.0, 24.0),
                           target=(0.0, 0.35, 0.0))
    for a, b in zip(default, explicit, strict=True):
        torch.testing.assert_close(a.world_to_camera, b.world_to_camera, rtol=0, atol=0)
        torch.testing.assert_close(a.intrinsics, b.intrinsics, rtol=0, atol=0)
    # by hand: fov 50 deg over 16 px -> fx = 8 / tan(25 deg) = 17.1560...
    assert float(default[0].intrinsics[0, 0]) == pytest.approx(8 / np.tan(np.radians(25.0)), rel=1e-6)
    # the camera distance to the target oscillates within the default radius bounds and reaches both
    target = torch.tensor([0.0, 0.35, 0.0], dtype=default[0].center.dtype)
    dist = [float((c.center - target).norm()) for c in default]
    assert min(dist) == pytest.approx(4.2, abs=1e-5) and max(dist) == pytest.approx(5.2, abs=1e-5)


def test_load_builtin_scene_defaults_32_views_every_8th_tested_4x4_samples_fov_50():
    from controlgs_adapter.scene.diorama import load_builtin_scene
    from controlgs_adapter.scene.planes import render_planes

    scene = load_builtin_scene(resolution=16)  # default variant "ar", views 32, test_every 8, samples 4, fov 50
    assert scene.variant == "ar" and scene.resolution == 16
    assert len(scene.train_cameras) == 28 and len(scene.test_cameras) == 4  # views 0, 8, 16, 24 are tested
    cams = arc_cameras(32, size=16, fov_deg=50.0)
    for got, want in zip(scene.test_cameras, cams[0::8], strict=True):
        torch.testing.assert_close(got.world_to_camera, want.world_to_camera, rtol=0, atol=0)
        torch.testing.assert_close(got.intrinsics, want.intrinsics, rtol=0, atol=0)
    torch.testing.assert_close(scene.train_cameras[0].world_to_camera, cams[1].world_to_camera, rtol=0, atol=0)
    # the ground truth is rendered with 4 x 4 samples over a black background (render_planes' defaults)
    img4 = render_planes(scene.planes, cams[8])[0].float()
    torch.testing.assert_close(scene.test_images[1], img4, rtol=0, atol=1e-6)
    torch.testing.assert_close(render_planes(scene.planes, cams[8], samples=4, background=(0.0, 0.0, 0.0))[0].float(),
                               img4, rtol=0, atol=0)
    assert float((render_planes(scene.planes, cams[8], samples=1)[0].float() - img4).abs().max()) > 1e-3
    # points(): default spacing 0.05 (a coarser spacing gives fewer points)
    n_default = scene.points()[0].shape[0]
    assert n_default == scene.points(0.05)[0].shape[0] > scene.points(0.1)[0].shape[0]


def _two_cameras() -> SceneData:
    """Two 8 x 6 cameras at the origin (f = 4, centre (4, 3)): v0 looks down +z, v1 down -z."""
    frames = []
    for i, flip in enumerate((1.0, -1.0)):
        w2c = torch.eye(4)
        w2c[:3, :3] = torch.diag(torch.tensor([1.0, flip, flip]))
        k = torch.tensor([[4.0, 0, 4], [0, 4.0, 3], [0, 0, 1]])
        frames.append(Frame(f"v{i}", Camera(w2c, k, 8, 6), torch.zeros(3, 6, 8)))
    return SceneData({"train": frames}, source="src")


def test_check_scene_default_min_in_front_is_5_percent():
    from controlgs_adapter.datasets.sanity import check_scene

    # 100 points: 5 straight ahead of v0 (5 % -> not blind: the threshold is strict), 4 straight ahead of
    # v1 (4 % -> blind), 91 far to the side (outside both images or behind)
    pts = torch.cat([torch.tensor([[0.0, 0, 1]]).repeat(5, 1), torch.tensor([[0.0, 0, -1]]).repeat(4, 1),
                     torch.tensor([[10.0, 0, 1]]).repeat(91, 1)])
    data = _two_cameras()
    with pytest.warns(RuntimeWarning, match=r"^src: 1 of 2 cameras see almost none of the 100 points \(< 5% in front, "
                                            r"inside the image\): v1$"):
        rep = check_scene(data, pts)
    assert rep["in_front"] == pytest.approx({"v0": 0.05, "v1": 0.04}, abs=1e-6) and rep["blind"] == ["v1"]
    assert check_scene(data, pts, min_in_front=0.035)["blind"] == []
    with pytest.raises(InputValueError, match=r"^src: 2 of 2 cameras see none of the scene"):
        check_scene(data, pts, min_in_front=0.051)
    # default required=("train",): an empty test split passes, an empty train split is refused
    with pytest.raises(InputValueError, match=r"^src: the 'train' split is empty \(splits: train=0, test=2\)$"):
        check_scene(SceneData({"train": [], "test": data.splits["train"]}, source="src"))


def test_load_dataset_passes_holdout_and_refuses_images_for_other_formats(tmp_path):
    _ngp(tmp_path)
    assert _test_names(load_dataset(tmp_path, holdout=3)) == ["images/img_00.png", "images/img_03.png",
                                                              "images/img_06.png", "images/img_09.png"]
    assert _test_names(load_dataset(tmp_path, format=" Instant-NGP ", holdout=0)) == []
    with pytest.raises(InputValueError, match=rf"^images='imgs' applies to COLMAP datasets only; {tmp_path} is read as instant_ngp$"):
        load_dataset(tmp_path, images="imgs")
    with pytest.raises(InputValueError, match=r"^format must be one of colmap, blender, instant_ngp \(or None to detect it\), got 'nerf'$"):
        load_dataset(tmp_path, format="nerf")
    # background overrides white_background through load_dataset too (ngp frames are RGB: check the setting)
    data = load_dataset(tmp_path, background=torch.tensor([0.2, 0.3, 0.4]), white_background=True)
    assert data.background.tolist() == pytest.approx([0.2, 0.3, 0.4])
    assert load_dataset(tmp_path).background.tolist() == [0.0, 0.0, 0.0]
    assert load_dataset(tmp_path, white_background=True).background.tolist() == [1.0, 1.0, 1.0]


def test_colmap_default_holdout_8_and_resolution_through_load_dataset(tmp_path):
    from _scene_writers import write_colmap
    from controlgs_adapter.datasets.colmap import read_colmap

    cams = arc_cameras(10, size=16)
    images = [torch.full((3, 16, 16), i / 10.0) for i in range(10)]
    root = write_colmap(tmp_path / "c", cams, images)
    want = ["v00.png", "v08.png"]  # every 8th of v00..v09 by name
    assert _test_names(read_colmap(root)) == want
    assert _test_names(load_dataset(root)) == want
    assert _test_names(load_dataset(root, holdout=4)) == ["v00.png", "v04.png", "v08.png"]
    # resolution reaches read_colmap: it picks images_2 (8 x 8 files, still >= 8) and the cameras follow
    from _scene_writers import save_png

    for i in range(10):
        save_png(root / "images_2" / f"v{i:02d}.png", torch.full((3, 8, 8), i / 10.0))
    assert load_dataset(root).splits["train"][0].camera.width == 16
    assert load_dataset(root, resolution=8).splits["train"][0].camera.width == 8


def test_ply_columns_default_count_takes_every_numbered_column():
    from controlgs_adapter.formats.backbone import ply_columns

    fields = {"f_0": np.array([1.0, 2.0]), "f_2": np.array([5.0, 6.0]), "f_1": np.array([3.0, 4.0]),
              "f_rest": np.array([9.0, 9.0]), "x": np.zeros(2)}
    got = ply_columns(fields, "f_", source="a.ply")
    assert got.dtype == np.float32 and got.tolist() == [[1.0, 3.0, 5.0], [2.0, 4.0, 6.0]]
    assert ply_columns(fields, "f_", source="a.ply", count=2).tolist() == [[1.0, 3.0], [2.0, 4.0]]
    del fields["f_1"]
    with pytest.raises(FileFormatError, match=r"^a.ply: PLY fields f_\* are not numbered 0..n-1 \(missing f_1\)$"):
        ply_columns(fields, "f_", source="a.ply")


def test_posed_images_defaults_1_gib_cache_views_name_black_background():
    from controlgs_adapter.datasets.base import PosedImages

    with pytest.raises(InputValueError, match=r"^views: no frames$"):
        PosedImages([])
    data = _two_cameras()
    p = PosedImages(data.splits["train"])
    assert p.cache_bytes == 1 << 30 == 1073741824 and p.name == "views" and p.background.tolist() == [0.0, 0.0, 0.0]
    v = data.views("train")  # SceneData.views: the same cache budget, named source:split, full size
    assert (v.cache_bytes, v.name, v.camera(0).width) == (1 << 30, "src:train", 8)
    assert data.views("train", cache_bytes=0).cache_bytes == 0
    assert len(data.views("train", first=1)) == 1 and len(v) == 2


def test_memory_frames_default_names():
    from controlgs_adapter.datasets.memory import posed_images, tensor_frames

    cams = [_two_cameras().splits["train"][0].camera] * 2
    imgs = torch.zeros(2, 3, 6, 8)
    assert [f.name for f in tensor_frames(imgs, cams)] == ["view/0000", "view/0001"]
    assert [f.name for f in tensor_frames(imgs, cams, prefix="p")] == ["p/0000", "p/0001"]
    p = posed_images(imgs, cams)
    assert p.name == "views" and [f.name for f in p.frames] == ["views/0000", "views/0001"]
    assert p.background.tolist() == [0.0, 0.0, 0.0]


def test_look_at_default_up_is_world_y():
    from controlgs_adapter.scene.cameras import look_at

    cam = look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), size=16, fov_deg=60.0)
    # world +y above the target projects above the image centre (v < 8), world +x to the right (u > 8)
    uv, z = cam.project(torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]))
    assert float(uv[0, 1]) < 8.0 and float(uv[0, 0]) == pytest.approx(8.0, abs=1e-5)
    assert float(uv[1, 0]) > 8.0 and float(uv[1, 1]) == pytest.approx(8.0, abs=1e-5)
    # with up = world x, world +x is the one that appears upward
    cam_x = look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), size=16, fov_deg=60.0, up=(1.0, 0.0, 0.0))
    assert float(cam_x.project(torch.tensor([[1.0, 0.0, 0.0]]))[0][0, 1]) < 8.0


def test_textured_plane_make_defaults_face_plus_z_once():
    from controlgs_adapter.scene.planes import TexturedPlane

    p = TexturedPlane.make("p", "brick", (0.0, 0.0, 0.0), 2.0, 1.0)
    # yaw 0, pitch 0: right = (w/2, 0, 0), down = (0, -h/2, 0); repeat (1, 1)
    assert p.right.tolist() == [1.0, 0.0, 0.0] and p.down.tolist() == [0.0, -0.5, 0.0]
    assert tuple(p.repeat) == (1, 1)
    assert p.normal.abs().tolist() == [0.0, 0.0, 1.0]


def test_undistort_points_default_20_iterations_converge():
    k = torch.tensor([[300.0, 0, 160], [0, 280.0, 120], [0, 0, 1]], dtype=torch.float64)
    dist = (-0.3, 0.1, 0.002, -0.001, 0.02)
    uv = torch.tensor([[5.0, 7.0], [310.0, 230.0]], dtype=torch.float64)
    default = undistort_points(uv, k, dist)
    assert torch.equal(default, undistort_points(uv, k, dist, iterations=20))
    assert not torch.allclose(default, undistort_points(uv, k, dist, iterations=1), atol=1e-6)
    # converged: distorting the result gives back the input
    xy = torch.stack([(default[:, 0] - 160) / 300, (default[:, 1] - 120) / 280], dim=-1)
    d = distort_normalized(xy, dist)
    torch.testing.assert_close(torch.stack([300 * d[:, 0] + 160, 280 * d[:, 1] + 120], dim=-1), uv, rtol=0, atol=1e-9)


def test_builtin_backbone_default_variant_is_ar():
    from controlgs_adapter.scene.backbone import builtin_backbone_dir

    assert builtin_backbone_dir() == builtin_backbone_dir("ar") != builtin_backbone_dir("vr")
    assert builtin_backbone_dir().name == "ar"


def test_decoders_from_state_dicts_default_nothing_optional():
    from controlgs_adapter.formats.decoders import decoders_from_state_dicts

    lin = nn.Sequential(nn.Linear(4, 3), nn.ReLU(), nn.Linear(3, 2))
    sd = {"mlp_opacity": lin.state_dict()}
    keys = {"mlp_opacity": "mlp_opacity", "mlp_cov": "mlp_cov"}
    with pytest.raises(FileFormatError, match=r"^ckpt.pth: missing entry 'mlp_cov' \(has \['mlp_opacity'\]\)$"):
        decoders_from_state_dicts(sd, keys, source="ckpt.pth")
    out = decoders_from_state_dicts(sd, keys, source="ckpt.pth", optional=("mlp_cov",))
    assert list(out) == ["mlp_opacity"]
    x = torch.randn(5, 4)
    torch.testing.assert_close(out["mlp_opacity"](x), torch.tanh(lin(x)))  # Scaffold-GS: ReLU between, Tanh after
