"""The generated demo scene: determinism, the 12/12 split, seed points on the analytic surfaces, exact images."""

import dataclasses
import hashlib
import json

import numpy as np
import pytest
import torch

from kc_splatfacto.data import resolve_dataparser
from kc_splatfacto.data.base import DataParserError
from kc_splatfacto.data.dataset import ImageDataset
from kc_splatfacto.data.demo import (
    DemoDataParserConfig,
    DemoSceneSpec,
    arc_cameras,
    build_scene,
    ensure_demo_scene,
    render_view,
)
from kc_splatfacto.data.images import read_image


@pytest.fixture(scope="module")
def demo_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("demo_cache")


@pytest.fixture(scope="module")
def demo_parser(demo_cache):
    return DemoDataParserConfig(demo_cache_dir=demo_cache).setup()


def box_sdf(points, center, half_size, yaw):
    """Signed distance to an oriented box (independent of the generator's ray caster)."""
    c, s = np.cos(yaw), np.sin(yaw)
    local = (points - center) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    q = np.abs(local) - half_size
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


def scene_distance(points, scene):
    dists = [np.abs(points @ p.normal - p.offset) for p in scene.planes]
    dists += [np.abs(box_sdf(points, b.center, b.half_size, b.yaw)) for b in scene.boxes]
    return np.min(np.stack(dists), axis=0)


def test_demo_split_is_12_train_12_test_alternating(demo_parser):
    train = demo_parser.get_dataparser_outputs("train")
    test = demo_parser.get_dataparser_outputs("test")
    val = demo_parser.get_dataparser_outputs("val")
    assert len(train.image_filenames) == 12 and len(test.image_filenames) == 12
    train_ids = [int(p.stem) for p in train.image_filenames]
    test_ids = [int(p.stem) for p in test.image_filenames]
    assert train_ids == list(range(0, 24, 2)) and test_ids == list(range(1, 24, 2))
    assert val.image_filenames == test.image_filenames
    assert int(train.cameras.widths[0]) == 160 and int(train.cameras.heights[0]) == 120
    assert train.points3d_xyz.shape == (2000, 3) and train.points3d_rgb.dtype == torch.uint8
    # normalized camera centres inside the unit cube, the largest coordinate exactly 1
    centers = torch.cat([train.cameras.centers(), test.cameras.centers()])
    assert centers.abs().max().item() == pytest.approx(1.0, abs=1e-5)


def test_demo_regenerated_with_same_seed_is_identical(tmp_path):
    small = {"width": 64, "height": 48, "num_points": 300}
    first = DemoDataParserConfig(demo_cache_dir=tmp_path / "a", **small).setup().get_dataparser_outputs("train")
    again = DemoDataParserConfig(demo_cache_dir=tmp_path / "b", **small).setup().get_dataparser_outputs("train")
    assert first.image_filenames[0].parent != again.image_filenames[0].parent  # really generated twice
    for a, b in zip(first.image_filenames, again.image_filenames):
        assert np.array_equal(read_image(a), read_image(b))
    assert torch.equal(first.cameras.viewmats, again.cameras.viewmats)
    assert torch.equal(first.points3d_xyz, again.points3d_xyz)
    other = DemoDataParserConfig(demo_cache_dir=tmp_path / "c", seed=1, num_cameras=2, **small).setup()
    other_image = read_image(other.get_dataparser_outputs("train").image_filenames[0])
    assert not np.array_equal(read_image(first.image_filenames[0]), other_image)


def test_demo_seed_points_lie_on_the_analytic_surfaces(demo_parser):
    outputs = demo_parser.get_dataparser_outputs("train")
    normalization = outputs.metadata["normalization"]
    world = normalization.invert_points(outputs.points3d_xyz.double().numpy())
    dist = scene_distance(world, build_scene(0))
    noise = DemoSceneSpec().point_noise
    # |N(0, s^2 I)| projected on a normal is N(0, s^2): 5 sigma bounds every one of 2000 points
    assert dist.max() < 5 * noise
    assert 0.3 * noise < np.median(dist) < 1.2 * noise  # the noise is really there, at the documented scale


def test_demo_seed_points_project_onto_their_surfaces_with_their_colour(demo_parser):
    """Project seed points with the parsed (normalized) cameras: where the surface is visible, the rendered depth
    matches the point's depth and the image colour matches the point's colour."""
    outputs = demo_parser.get_dataparser_outputs("train")
    dataset = ImageDataset(outputs)
    scene = build_scene(0)
    c2ws, intrinsics = arc_cameras(24, 160, 120)
    scale = outputs.dataparser_scale
    xyz = outputs.points3d_xyz.double()
    depth_errors, colour_errors = [], []
    for view in (0, 5, 11):
        viewmat = outputs.cameras.viewmats[view].double()
        cam = xyz @ viewmat[:3, :3].T + viewmat[:3, 3]
        uv = cam @ outputs.cameras.Ks[view].double().T
        uv = (uv[:, :2] / uv[:, 2:]).numpy()
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < 160) & (uv[:, 1] >= 0) & (uv[:, 1] < 120) & (cam[:, 2].numpy() > 0)
        _, depth = render_view(scene, c2ws[2 * view], intrinsics, 160, 120)  # train view i is arc camera 2i
        cols, rows = uv[inside, 0].astype(int), uv[inside, 1].astype(int)
        point_depth = cam[inside, 2].numpy() / scale  # back to scene units
        visible = np.abs(depth[rows, cols] - point_depth) < 0.1
        assert visible.mean() > 0.6  # most seed points are seen by the views they were sampled from
        depth_errors.append(np.abs(depth[rows, cols] - point_depth)[visible])
        image = dataset.image_uint8(view).numpy().astype(float)
        colour_errors.append(np.abs(image[rows, cols] - outputs.points3d_rgb[inside].numpy())[visible].mean(axis=1))
    assert np.median(np.concatenate(depth_errors)) < 0.03
    assert np.median(np.concatenate(colour_errors)) < 25  # 8-bit levels; sharp texture edges make some large


def test_demo_images_are_heavy_tailed_like_photos(demo_parser):
    """Finest-scale horizontal differences (a Haar detail band) have kurtosis well above a Gaussian's 3."""
    outputs = demo_parser.get_dataparser_outputs("train")
    gray = read_image(outputs.image_filenames[0]).astype(float).mean(axis=2)
    detail = (gray[:, 1::2] - gray[:, 0::2]).ravel()
    detail = detail - detail.mean()
    kurtosis = np.mean(detail**4) / np.mean(detail**2) ** 2
    assert kurtosis > 6.0


def test_resolve_dataparser_demo_uses_the_cache_env(monkeypatch, tmp_path):
    monkeypatch.setenv("KC_SPLATFACTO_CACHE", str(tmp_path))
    config = resolve_dataparser("demo")
    assert isinstance(config, DemoDataParserConfig)
    config.num_cameras = 4  # resizable and fast
    config.width, config.height = 32, 24
    config.num_points = 50
    outputs = config.setup().get_dataparser_outputs("train")
    assert outputs.image_filenames[0].is_relative_to(tmp_path / "demo")
    assert len(outputs.image_filenames) == 2 and int(outputs.cameras.widths[0]) == 32
    assert not list((tmp_path / "demo").glob(".*"))  # the temp generation folder is gone


def test_demo_spec_rejects_bad_sizes(tmp_path):
    with pytest.raises(DataParserError, match="width = 4 is not allowed: it must be at least 8"):
        ensure_demo_scene(DemoSceneSpec(width=4, height=4), tmp_path)
    with pytest.raises(DataParserError, match="num_cameras = 1 is not allowed: it must be at least 2"):
        ensure_demo_scene(DemoSceneSpec(num_cameras=1), tmp_path)


def test_unwritable_cache_is_a_clear_error(monkeypatch, tmp_path):
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("a file where the cache folder should be")
    monkeypatch.setenv("KC_SPLATFACTO_CACHE", str(blocker))
    with pytest.raises(DataParserError, match="cannot write the demo scene .*KC_SPLATFACTO_CACHE"):
        resolve_dataparser("demo").setup()


# ------------------------------------------------------------------------------------------------ one home for the
# scene's fields (issue 38): DemoSceneSpec holds them, DemoDataParserConfig inherits them; caches, scenes, flags and
# config.yml files of earlier versions stay valid.

SPEC_FIELDS = ("seed", "width", "height", "num_cameras", "num_points", "point_noise")
#: DemoDataParserConfig's fields in the order the command line and config.yml have always listed them
CONFIG_FIELDS = ("data", "downscale_factor", "orientation_method", "center_method", "auto_scale_poses",
                 "allow_symlinks_out", "cache_dir", "images_path", "colmap_path", "load_3d_points", "masks_path",
                 *SPEC_FIELDS, "demo_cache_dir")


def scene_digest(folder):
    """Digest of a scene folder's files: decoded pixels of the PNGs (the encoder's bytes are the codec's business),
    the bytes of every other file (lists, COLMAP text model, demo.json)."""
    digest = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        digest.update(str(path.relative_to(folder)).encode())
        digest.update(read_image(path).tobytes() if path.suffix == ".png" else path.read_bytes())
    return digest.hexdigest()[:16]


def test_the_scene_fields_are_written_once():
    assert tuple(f.name for f in dataclasses.fields(DemoSceneSpec)) == SPEC_FIELDS
    assert tuple(f.name for f in dataclasses.fields(DemoDataParserConfig)) == CONFIG_FIELDS
    for name in SPEC_FIELDS:  # the config's field is the spec's own Field: one default, one docstring
        assert DemoDataParserConfig.__dataclass_fields__[name] is DemoSceneSpec.__dataclass_fields__[name]
    config = DemoDataParserConfig(seed=5, width=40, height=30, num_cameras=4, num_points=50, point_noise=0.25)
    assert type(config.spec()) is DemoSceneSpec
    assert config.spec() == DemoSceneSpec(5, 40, 30, 4, 50, 0.25)


@pytest.mark.parametrize(
    "values, key",  # the keys the code before the merge gave: cached scenes keep their folder
    [({}, "demo-v3-seed0-160x120-cams24-pts2000-noise0.01"),
     ({"width": 64, "height": 48, "num_points": 300}, "demo-v3-seed0-64x48-cams24-pts300-noise0.01"),
     ({"seed": 3, "width": 33, "height": 17, "num_cameras": 3, "num_points": 7, "point_noise": 0.0},
      "demo-v3-seed3-33x17-cams3-pts7-noise0"),
     ({"width": 40, "height": 30, "num_cameras": 4, "num_points": 50, "point_noise": 1.25e-7},
      "demo-v3-seed0-40x30-cams4-pts50-noise1.25e-07")],
)
def test_the_cache_key_is_unchanged(values, key):
    assert DemoSceneSpec(**values).key() == key
    assert DemoDataParserConfig(**values).spec().key() == key
    assert DemoDataParserConfig(**values).key() == key


def test_the_generated_scene_is_unchanged(demo_parser, tmp_path):
    """Digests of the v3 scenes: the same on every CPU kind (the generator makes no BLAS call and snaps library
    results, kc_splatfacto/data/demo.py), checked on Zen 4 (AVX-512) and as an AVX2 and an SSE3 machine would run it
    (test_the_scene_does_not_depend_on_the_cpu_kind); v2's pixels differed between AVX-512 and AVX2 machines."""
    assert scene_digest(demo_parser.config.data) == "66dff9767e122164"  # the default scene, 160x120
    small = DemoDataParserConfig(demo_cache_dir=tmp_path, width=40, height=30, num_cameras=4, num_points=50,
                                 point_noise=0.1)
    folder = small.setup().config.data
    assert folder == tmp_path / "demo-v3-seed0-40x30-cams4-pts50-noise0.1"
    assert scene_digest(folder) == "1495b2ee46dfb6ed"
    assert json.loads((folder / "demo.json").read_text()) == {"version": 3, **dataclasses.asdict(small.spec())}


#: what another CPU kind changes, forced on this one: OpenBLAS's kernels (the v2 scene's cause: its pixels followed
#: them), numpy's dispatched SIMD loops, torch's vector width; docs/architecture.md ("Testing") runs the suite so
AS_OTHER_CPU = {
    "x86_64": [{"OPENBLAS_CORETYPE": "Prescott", "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR",
                "ATEN_CPU_CAPABILITY": "default"},
               {"OPENBLAS_CORETYPE": "Haswell", "ATEN_CPU_CAPABILITY": "avx2"}],
    "aarch64": [{"OPENBLAS_CORETYPE": "ARMV8", "ATEN_CPU_CAPABILITY": "default"}],
}

DIGEST_SCRIPT = """
import hashlib, sys
from pathlib import Path
from kc_splatfacto.data.demo import DemoDataParserConfig
from kc_splatfacto.data.images import read_image
folder = DemoDataParserConfig(demo_cache_dir=Path(sys.argv[1]), width=40, height=30, num_cameras=4, num_points=50,
                              point_noise=0.1).setup().config.data
digest = hashlib.sha256()
for path in sorted(p for p in folder.rglob("*") if p.is_file()):
    digest.update(str(path.relative_to(folder)).encode())
    digest.update(read_image(path).tobytes() if path.suffix == ".png" else path.read_bytes())
print(digest.hexdigest()[:16])
"""


@pytest.mark.parametrize("index", [0, 1])
def test_the_scene_does_not_depend_on_the_cpu_kind(tmp_path, index):
    """The small scene generated as another CPU kind would generate it (in a fresh process: the libraries read these
    variables when they load) has the digest this process gives: v2's (7cf36467099608a2 on AVX-512) became
    e5123973609d9c3b under OPENBLAS_CORETYPE=Haswell, exactly what an AVX2 machine wrote."""
    import os
    import platform
    import subprocess
    import sys

    kinds = AS_OTHER_CPU.get(platform.machine())
    if kinds is None or index >= len(kinds):
        pytest.skip(f"no emulated CPU kind {index} known for {platform.machine()}")
    env = {**os.environ, **kinds[index]}
    out = subprocess.run([sys.executable, "-c", DIGEST_SCRIPT, str(tmp_path / "other")], env=env, text=True,
                         capture_output=True, check=True).stdout.strip()
    here = DemoDataParserConfig(demo_cache_dir=tmp_path / "here", width=40, height=30, num_cameras=4, num_points=50,
                                point_noise=0.1).setup().config.data
    assert out == scene_digest(here) == "1495b2ee46dfb6ed"


#: the dataparser part of a config.yml the code before the merge wrote (kc-train splatfacto --data demo demo ...)
OLD_CONFIG_YML = """\
!!python/object:kc_splatfacto.data.demo.DemoDataParserConfig
data: !!python/object/apply:pathlib.PosixPath
- demo
downscale_factor: 1
orientation_method: up
center_method: poses
auto_scale_poses: true
allow_symlinks_out: false
cache_dir: null
images_path: null
colmap_path: null
load_3d_points: true
masks_path: null
seed: 2
width: 64
height: 48
num_cameras: 6
num_points: 100
point_noise: 0.02
demo_cache_dir: null
"""


def test_flags_and_config_yml_of_earlier_runs_give_the_same_config(tmp_path):
    from kc_splatfacto.cli.train import parse_config
    from kc_splatfacto.engine.config_file import load_yaml, save_config

    flags = ["--seed", "2", "--width", "64", "--height", "48", "--num-cameras", "6", "--num-points", "100",
             "--point-noise", "0.02"]
    parsed = parse_config(["splatfacto", "--data", "demo", "demo", *flags]).pipeline.datamanager.dataparser
    expected = DemoDataParserConfig(seed=2, width=64, height=48, num_cameras=6, num_points=100, point_noise=0.02)
    assert parsed == expected
    assert load_yaml(OLD_CONFIG_YML) == expected  # the strict reader: every key a field, the class where it was
    save_config(expected, tmp_path / "config.yml")
    assert (tmp_path / "config.yml").read_text() == OLD_CONFIG_YML  # and written as before, field for field


#: the demo subcommand's scene flags as ``--help`` showed them before the merge (whitespace folded)
HELP_LINES = (
    "--seed INT Generator seed: the same seed gives identical images, cameras and points. (default: 0)",
    "--width INT image width in pixels (default: 160)",
    "--height INT image height in pixels (default: 120)",
    "--num-cameras INT Cameras on the arc; even positions train, odd test. (default: 24)",
    "--num-points INT Seed points sampled from the surfaces seen by the train views. (default: 2000)",
    "--point-noise FLOAT Standard deviation of the Gaussian noise on seed points, scene units (the scene is about 9 "
    "units wide). (default: 0.01)",
)


def test_help_shows_the_scene_flags_as_before(capsys):
    from kc_splatfacto.cli.train import parse_config

    with pytest.raises(SystemExit):
        parse_config(["splatfacto", "--data", "demo", "demo", "--help"])
    shown = " ".join(capsys.readouterr().out.split())
    places = [shown.find(line) for line in HELP_LINES]
    assert -1 not in places and places == sorted(places), shown
    assert shown.find("--masks-path") < places[0] < places[-1] < shown.find("--demo-cache-dir")
