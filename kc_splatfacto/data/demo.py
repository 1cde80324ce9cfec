"""The generated demo scene (``--data demo``): exact numpy ray casting of boxes and planes, written as a SPARS3R scene.

The scene (world z up, units arbitrary, about 9 wide): a ground plane, a back wall and three rotated boxes. Every
surface carries a natural-image-like texture: a dead-leaves layer (random discs and rectangles with power-law sizes,
so sharp occlusion edges at every scale) plus 1/f Gaussian noise; wavelet detail coefficients of such images are
heavy-tailed like photographs'. Shading is a fixed per-face Lambert factor (view independent). A pixel is the mean
of 2x2 ray-cast samples at offsets 0.25/0.75 (pixel centres at +0.5) with bilinear texture lookups, so the images
are exact functions of the scene, with no rasterizer involved.

The same bytes on every CPU: the generator makes no BLAS call (numpy's ``@``, ``dot`` and ``linalg.norm`` run
OpenBLAS kernels picked per CPU, whose summation orders differ: that alone made the v2 scene's pixels differ between
AVX-512 and AVX2 machines), only elementwise IEEE operations (``+ - * /``, ``sqrt``, exactly rounded everywhere) on
values that are snapped to a dyadic grid wherever a library function that may differ in its last bit (``sin``,
``cos``, ``pow``, the FFT) made them, so that such a difference cannot reach the pixels (:func:`snap`).

24 cameras on an arc in front of the scene look at its centre; even positions are train, odd are test (SPARS3R's
alternation, 12/12). Seed points are exact surface points seen by random pixels of the train views, with their
rendered colour, moved by isotropic Gaussian noise of ``point_noise`` (scene units).

Generated on first use into ``$KC_SPLATFACTO_CACHE/demo/<key>/`` (``~/.cache/kc_splatfacto``): written into a temp
folder and renamed into place, so a crash or a concurrent run never leaves a half scene. The folder is a SPARS3R
scene (``images/``, ``train_list.txt``, ``test_list.txt``, ``sparse/0/*.txt``) read back by the SPARS3R parser.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import torch

from kc_splatfacto.data.base import CACHE_ENV, DataParserError, default_cache_dir
from kc_splatfacto.data.images import write_image_atomic
from kc_splatfacto.data.spars3r import Spars3rDataParser, Spars3rDataParserConfig
from kc_splatfacto.registry import DataParserSpecification
from kc_splatfacto.render.projection import rotmat_to_quat
from kc_splatfacto.settings import SEED_MAX, integer, range_violations, real, setting

# Bump when the generator changes: it is part of the cache key, so stale scenes are never reused.
DEMO_VERSION = 3  # 3: no BLAS, snapped library values (the same bytes on every CPU); 2: rotmat_to_quat's quaternions
MIN_SIZE = 8
"""the smallest demo image side in pixels"""
TEXTURE_SIZE = 256
TEXEL_SIZE = 1.0 / 40.0  # scene units per texel; a texture tile covers 6.4 units and repeats
SUBSAMPLE_OFFSETS = (0.25, 0.75)
RAY_EPS = 1e-6
LIGHT_DIRECTION = np.array([0.4, -0.6, 0.7]) / math.sqrt(0.4 * 0.4 + 0.6 * 0.6 + 0.7 * 0.7)
SKY_RGB = np.array([0.62, 0.72, 0.85])




def snap(values, bits: int):
    """``values`` rounded to multiples of 2^-bits: exact operations (a power-of-two scale, round-half-even), so a
    value a library function computed 1 ulp differently on another CPU lands on the same grid point unless it lies
    within that ulp of a midpoint (a chance of about 2^(bits-52) per value)."""
    scale = float(2**bits)
    return np.round(np.asarray(values, np.float64) * scale) / scale


#: grids for library results: trigonometry of poses (~1e2 values, 2^-32: ~1e-8 chance of a flip in a scene) and
#: the textures (~1e6 values after the FFT, 2^-20 = 1e-6 of the colour range: ~2e-4 chance)
POSE_BITS = 32
TEXTURE_BITS = 20


def dot3(vectors: np.ndarray, vector: np.ndarray) -> np.ndarray:
    """[K,3] rows dotted with one [3] vector, elementwise in a fixed order (not BLAS: see the module docstring)."""
    return vectors[..., 0] * vector[0] + vectors[..., 1] * vector[1] + vectors[..., 2] * vector[2]


def norm3(vector: np.ndarray) -> float:
    """Euclidean norm of a [3] vector, without BLAS."""
    return math.sqrt(float(vector[0] * vector[0] + vector[1] * vector[1] + vector[2] * vector[2]))


@dataclass
class Plane:
    """Points ``x`` with ``normal . x = offset``; texture coordinates along ``u_axis`` and ``v_axis``."""

    normal: np.ndarray
    offset: float
    u_axis: np.ndarray
    v_axis: np.ndarray
    texture: int


@dataclass
class Box:
    """An oriented box: ``center`` [3], ``half_size`` [3], rotation ``yaw`` about z (radians)."""

    center: np.ndarray
    half_size: np.ndarray
    yaw: float
    texture: int

    @property
    def rotation(self) -> np.ndarray:
        """[3,3] box-to-world rotation (columns are the box axes in world)."""
        c, s = snap([math.cos(self.yaw), math.sin(self.yaw)], POSE_BITS)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class DemoScene:
    """Primitives and textures ([T, S, S, 3] float64 in [0,1]) of a generated scene."""

    planes: list[Plane]
    boxes: list[Box]
    textures: np.ndarray
    seed: int = 0
    extras: dict = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------------------------
# Textures
# ----------------------------------------------------------------------------------------------------------------


def pink_noise(rng: np.random.Generator, size: int) -> np.ndarray:
    """[size, size] periodic Gaussian noise with a 1/f amplitude spectrum, unit standard deviation."""
    freq = np.fft.fftfreq(size)
    radius = np.sqrt(freq[:, None] ** 2 + freq[None, :] ** 2)
    radius[0, 0] = np.inf
    spectrum = (rng.standard_normal((size, size)) + 1j * rng.standard_normal((size, size))) / radius
    field_ = np.real(np.fft.ifft2(spectrum))
    return (field_ - field_.mean()) / (field_.std() + 1e-12)


def dead_leaves_texture(rng: np.random.Generator, size: int = TEXTURE_SIZE, num_shapes: int = 260) -> np.ndarray:
    """[size, size, 3] periodic texture: occluding discs/rectangles with power-law radii, plus 1/f noise."""
    palette = rng.uniform(0.05, 0.95, size=(5, 3))
    image = np.empty((size, size, 3))
    image[:] = palette[0]
    # Radii ~ r^-3 between r_min and r_max (scale invariance of natural images), drawn large-first so small
    # shapes end up on top, as in the dead-leaves model seen from above.
    r_min, r_max = 2.0, size / 5.0
    u = rng.uniform(size=num_shapes)
    radii = np.sort(snap((r_min**-2 - u * (r_min**-2 - r_max**-2)) ** -0.5, POSE_BITS))[::-1]
    for radius in radii:
        cx, cy = rng.uniform(0, size, size=2)
        colour = palette[rng.integers(len(palette))] * rng.uniform(0.7, 1.15) + rng.normal(0, 0.04, 3)
        r = math.ceil(radius)
        ys = np.arange(int(cy) - r, int(cy) + r + 1)
        xs = np.arange(int(cx) - r, int(cx) + r + 1)
        dy, dx = ys[:, None] + 0.5 - cy, xs[None, :] + 0.5 - cx
        if rng.uniform() < 0.6:
            inside = dx * dx + dy * dy <= radius * radius
        else:
            aspect = rng.uniform(0.3, 1.0)
            inside = (np.abs(dx) <= radius) & (np.abs(dy) <= radius * aspect)
        rows, cols = np.nonzero(inside)
        image[ys[rows] % size, xs[cols] % size] = colour
    noise = np.stack([pink_noise(rng, size) for _ in range(3)], axis=-1)
    lum = pink_noise(rng, size)[..., None]
    image = image + 0.05 * noise + 0.06 * lum
    return snap(np.clip(image, 0.0, 1.0), TEXTURE_BITS)


def sample_texture(texture: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear, periodic lookup at scene coordinates (u, v) [K] -> [K, 3]."""
    size = texture.shape[0]
    x = u / TEXEL_SIZE - 0.5
    y = v / TEXEL_SIZE - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x0 = x0.astype(np.int64) % size
    y0 = y0.astype(np.int64) % size
    x1, y1 = (x0 + 1) % size, (y0 + 1) % size
    return (
        texture[y0, x0] * (1 - fx) * (1 - fy)
        + texture[y0, x1] * fx * (1 - fy)
        + texture[y1, x0] * (1 - fx) * fy
        + texture[y1, x1] * fx * fy
    )


# ----------------------------------------------------------------------------------------------------------------
# Scene and cameras
# ----------------------------------------------------------------------------------------------------------------


def build_scene(seed: int = 0) -> DemoScene:
    """The demo scene's primitives and textures, deterministic from ``seed``."""
    rng = np.random.default_rng(seed)
    ex, ey, ez = np.eye(3)
    planes = [
        Plane(normal=ez, offset=0.0, u_axis=ex, v_axis=ey, texture=0),  # ground
        Plane(normal=-ey, offset=-2.5, u_axis=ex, v_axis=ez, texture=1),  # back wall, y = 2.5, faces the cameras
    ]
    boxes = []
    layout = [(-1.1, 0.2, 0.45), (0.5, 0.9, 0.7), (1.0, -0.6, 0.3)]
    for i, (x, y, h) in enumerate(layout):
        half = np.array([rng.uniform(0.35, 0.6), rng.uniform(0.35, 0.6), h])
        boxes.append(Box(center=np.array([x, y, h]), half_size=half, yaw=float(rng.uniform(-0.8, 0.8)), texture=2 + i))
    textures = np.stack([dead_leaves_texture(rng) for _ in range(2 + len(boxes))])
    return DemoScene(planes=planes, boxes=boxes, textures=textures, seed=seed)


def look_at_c2w(
    eye: np.ndarray, target: np.ndarray, world_up: tuple[float, float, float] = (0.0, 0.0, 1.0)
) -> np.ndarray:
    """[4,4] camera-to-world in OpenCV axes (x right, y down, z forward) looking from ``eye`` at ``target``."""
    forward = target - eye
    forward = forward / norm3(forward)
    right = np.cross(forward, np.asarray(world_up, np.float64))
    right = right / norm3(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, forward, eye
    return c2w


def arc_cameras(num_cameras: int, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """([N,4,4] OpenCV camera-to-world on an arc in front of the scene, [4] fx, fy, cx, cy for ``width``x``height``)."""
    angles = np.linspace(-math.radians(70), math.radians(70), num_cameras)
    target = np.array([0.0, 0.3, 0.45])
    c2ws = []
    for i, angle in enumerate(angles):
        radius = 4.2 + 0.3 * math.cos(3.0 * angle)
        eye = snap([radius * math.sin(angle), -radius * math.cos(angle), 1.5 + 0.25 * math.sin(2.0 * angle + i)],
                   POSE_BITS)
        c2ws.append(look_at_c2w(eye, target))
    focal = 0.9 * width  # about 58 degrees horizontal field of view
    return np.stack(c2ws), np.array([focal, focal, width / 2.0, height / 2.0])


# ----------------------------------------------------------------------------------------------------------------
# Ray casting
# ----------------------------------------------------------------------------------------------------------------


def _rotate(vectors: np.ndarray, rot: np.ndarray) -> np.ndarray:
    """[K,3] vectors times ``rot`` [3,3] (``rot @ v`` each), by broadcasting: no BLAS (its
    kernels, and so its rounding, depend on the CPU), which is also faster than tiny BLAS calls on a busy CPU."""
    return vectors[:, 0:1] * rot[:, 0] + vectors[:, 1:2] * rot[:, 1] + vectors[:, 2:3] * rot[:, 2]


def _rows(origins: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Origins of the selected rays: a shared [1,3] origin broadcasts, per-ray [K,3] origins are indexed."""
    return origins if len(origins) == 1 else origins[index]


def _intersect(primitive: Plane | Box, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Ray parameter of the first hit in front of the origin, [K] (inf where missed)."""
    if isinstance(primitive, Plane):
        denom = (directions * primitive.normal).sum(axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (primitive.offset - (origins * primitive.normal).sum(axis=1)) / denom
        return np.where((np.abs(denom) > 1e-12) & (t > RAY_EPS), t, np.inf)
    rot = primitive.rotation
    o_local = _rotate(origins - primitive.center, rot.T)
    d_local = _rotate(directions, rot.T)
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-primitive.half_size - o_local) / d_local
        t2 = (primitive.half_size - o_local) / d_local
    # 0/0 (a ray inside a slab plane) gives NaN: fmax/fmin ignore it, like an unbounded slab.
    t_near = np.fmax(
        np.fmax(np.minimum(t1[:, 0], t2[:, 0]), np.minimum(t1[:, 1], t2[:, 1])), np.minimum(t1[:, 2], t2[:, 2])
    )
    t_far = np.fmin(
        np.fmin(np.maximum(t1[:, 0], t2[:, 0]), np.maximum(t1[:, 1], t2[:, 1])), np.maximum(t1[:, 2], t2[:, 2])
    )
    return np.where((t_far >= t_near) & (t_near > RAY_EPS), t_near, np.inf)


def _surface(primitive: Plane | Box, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Texture coordinates (u [K], v [K]) and outward normals [K,3] at surface points [K,3]."""
    if isinstance(primitive, Plane):
        return dot3(points, primitive.u_axis), dot3(points, primitive.v_axis), np.broadcast_to(primitive.normal, points.shape)
    rot = primitive.rotation
    local = _rotate(points - primitive.center, rot.T)
    axis = np.argmax(np.abs(local) / primitive.half_size, axis=1)
    rows = np.arange(len(points))
    sign = np.sign(local[rows, axis])
    normal_local = np.zeros_like(local)
    normal_local[rows, axis] = sign
    # The two in-face axes, shifted per face so that the faces do not repeat each other's texture.
    u = local[rows, (axis + 1) % 3] + 1.7 * axis + 0.9 * (sign > 0)
    v = local[rows, (axis + 2) % 3] + 1.3 * axis
    return u, v, _rotate(normal_local, rot)


def cast_rays(scene: DemoScene, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of rays (origins [K,3] or a shared [1,3], directions [K,3]): (t [K] (inf = sky), rgb [K,3])."""
    primitives: list[Plane | Box] = [*scene.planes, *scene.boxes]
    ts = np.stack([_intersect(p, origins, directions) for p in primitives])
    winner = np.argmin(ts, axis=0)
    best_t = ts[winner, np.arange(len(directions))]
    rgb = np.tile(SKY_RGB, (len(directions), 1))
    for index, primitive in enumerate(primitives):
        idx = np.nonzero((winner == index) & np.isfinite(best_t))[0]
        if len(idx) == 0:
            continue
        points = _rows(origins, idx) + best_t[idx, None] * directions[idx]
        u, v, normal = _surface(primitive, points)
        colour = sample_texture(scene.textures[primitive.texture], u, v)
        shade = 0.55 + 0.45 * np.clip(dot3(normal, LIGHT_DIRECTION), 0.0, 1.0)
        rgb[idx] = colour * shade[:, None]
    return best_t, rgb


def camera_rays(c2w: np.ndarray, intrinsics: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World rays through pixel coordinates [K,2] (pixel centres at +0.5): (origin [1,3], unit directions [K,3]).

    The origin is shared (a pinhole), kept as one row so that per-ray work on it is done once.
    """
    fx, fy, cx, cy = intrinsics
    d_cam = np.stack([(pixels[:, 0] - cx) / fx, (pixels[:, 1] - cy) / fy, np.ones(len(pixels))], axis=1)
    d_world = _rotate(d_cam, c2w[:3, :3])
    d_world /= np.sqrt(d_world[:, 0:1] * d_world[:, 0:1] + d_world[:, 1:2] * d_world[:, 1:2]
                       + d_world[:, 2:3] * d_world[:, 2:3])
    return c2w[None, :3, 3].copy(), d_world


def render_view(
    scene: DemoScene, c2w: np.ndarray, intrinsics: np.ndarray, width: int, height: int, with_depth: bool = True
) -> tuple[np.ndarray, np.ndarray | None]:
    """Render one view: ([H,W,3] uint8 image, [H,W] float64 z-depth of the pixel-centre ray's hit, or None)."""
    jj, ii = np.meshgrid(np.arange(width), np.arange(height))
    pixels = np.concatenate(
        [np.stack([jj.ravel() + ox, ii.ravel() + oy], axis=1) for oy in SUBSAMPLE_OFFSETS for ox in SUBSAMPLE_OFFSETS]
    )
    origins, dirs = camera_rays(c2w, intrinsics, pixels)
    samples = cast_rays(scene, origins, dirs)[1].reshape(len(SUBSAMPLE_OFFSETS) ** 2, height * width, 3)
    image = np.round(np.clip(samples.mean(axis=0), 0, 1) * 255).astype(np.uint8).reshape(height, width, 3)
    if not with_depth:
        return image, None
    pixels = np.stack([jj.ravel() + 0.5, ii.ravel() + 0.5], axis=1)
    origins, dirs = camera_rays(c2w, intrinsics, pixels)
    t, _ = cast_rays(scene, origins, dirs)
    depth = (t * dot3(dirs, c2w[:3, 2])).reshape(height, width)
    return image, depth


def sample_seed_points(
    scene: DemoScene,
    c2ws: np.ndarray,
    intrinsics: np.ndarray,
    width: int,
    height: int,
    num_points: int,
    noise: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Surface points seen by random pixels of the given views: (noisy xyz [M,3], rgb uint8 [M,3], clean xyz [M,3])."""
    per_view = math.ceil(num_points / len(c2ws))
    clean, colours = [], []
    for c2w in c2ws:
        pixels = rng.uniform([0, 0], [width, height], size=(per_view * 2, 2))
        origins, dirs = camera_rays(c2w, intrinsics, pixels)
        t, rgb = cast_rays(scene, origins, dirs)
        hit = np.isfinite(t)
        points = _rows(origins, hit) + t[hit, None] * dirs[hit]
        clean.append(points[:per_view])
        colours.append(rgb[hit][:per_view])
    clean_xyz = np.concatenate(clean)[:num_points]
    rgb = np.round(np.clip(np.concatenate(colours)[:num_points], 0, 1) * 255).astype(np.uint8)
    noisy = clean_xyz + rng.normal(0.0, noise, size=clean_xyz.shape)
    return noisy, rgb, clean_xyz


# ----------------------------------------------------------------------------------------------------------------
# Writing the scene (SPARS3R layout, COLMAP text model)
# ----------------------------------------------------------------------------------------------------------------


def write_colmap_text_model(
    folder: Path,
    width: int,
    height: int,
    intrinsics: np.ndarray,
    names: list[str],
    c2ws: np.ndarray,
    points_xyz: np.ndarray,
    points_rgb: np.ndarray,
) -> None:
    """A one-camera PINHOLE COLMAP text model (no 2D observations) for the given OpenCV camera-to-worlds."""
    folder.mkdir(parents=True, exist_ok=True)
    fx, fy, cx, cy = intrinsics
    params = " ".join(repr(float(v)) for v in (fx, fy, cx, cy))
    (folder / "cameras.txt").write_text(f"# generated demo scene\n1 PINHOLE {width} {height} {params}\n")
    lines = ["# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then an empty POINTS2D line"]
    for image_id, (name, c2w) in enumerate(zip(names, c2ws), start=1):
        rot_cw = c2w[:3, :3].T
        t_cw = -_rotate(c2w[None, :3, 3], rot_cw)[0]
        q = rotmat_to_quat(torch.from_numpy(np.asarray(rot_cw, np.float64))[None])[0].numpy()
        lines.append(
            " ".join([str(image_id), *(repr(float(v)) for v in q), *(repr(float(v)) for v in t_cw), "1", name])
        )
        lines.append("")
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    point_lines = ["# POINT3D_ID X Y Z R G B ERROR (no tracks: the points are sampled, not triangulated)"]
    for point_id, (xyz, rgb) in enumerate(zip(points_xyz, points_rgb), start=1):
        coords = " ".join(repr(float(v)) for v in xyz)
        point_lines.append(f"{point_id} {coords} {int(rgb[0])} {int(rgb[1])} {int(rgb[2])} 0")
    (folder / "points3D.txt").write_text("\n".join(point_lines) + "\n")


@dataclass
class DemoSceneSpec:
    """What a generated demo scene depends on (its cache key): these fields, each written here only, are also the
    demo dataparser's (:class:`DemoDataParserConfig` inherits them: ``--width 64`` on the command line)."""

    seed: int = setting(0, integer(0, SEED_MAX))
    """Generator seed: the same seed gives identical images, cameras and points."""
    width: int = setting(160, integer(MIN_SIZE))
    """image width in pixels"""
    height: int = setting(120, integer(MIN_SIZE))
    """image height in pixels"""
    num_cameras: int = setting(24, integer(2))
    """Cameras on the arc; even positions train, odd test."""
    num_points: int = setting(2000, integer(1))
    """Seed points sampled from the surfaces seen by the train views."""
    point_noise: float = setting(0.01, real(0.0))
    """Standard deviation of the Gaussian noise on seed points, scene units (the scene is about 9 units wide)."""

    def key(self) -> str:
        return (
            f"demo-v{DEMO_VERSION}-seed{self.seed}-{self.width}x{self.height}-cams{self.num_cameras}"
            f"-pts{self.num_points}-noise{self.point_noise:g}"
        )

    def validate(self) -> None:
        """A :class:`DataParserError` naming the first field outside its range (the ranges beside the fields)."""
        for violation in range_violations(self):
            raise DataParserError(f"demo scene: {violation.name} = {violation.value!r} is not allowed: it must be "
                                  f"{violation.allowed}")


def spec_values(spec: DemoSceneSpec) -> dict:
    """{field: value} of the :class:`DemoSceneSpec` fields of ``spec`` (a spec, or a demo dataparser config), in
    their declared order."""
    return {f.name: getattr(spec, f.name) for f in fields(DemoSceneSpec)}


def generate_demo_scene(spec: DemoSceneSpec, folder: Path) -> Path:
    """Render and write the demo scene into ``folder`` (created; must not exist yet). Returns ``folder``."""
    spec.validate()
    scene = build_scene(spec.seed)
    c2ws, intrinsics = arc_cameras(spec.num_cameras, spec.width, spec.height)
    names = [f"{i:05d}.png" for i in range(spec.num_cameras)]
    (folder / "images").mkdir(parents=True)
    for name, c2w in zip(names, c2ws):
        image, _ = render_view(scene, c2w, intrinsics, spec.width, spec.height, with_depth=False)
        write_image_atomic(folder / "images" / name, image)
    train = names[0::2]
    test = names[1::2]
    (folder / "train_list.txt").write_text("\n".join(train) + "\n")
    (folder / "test_list.txt").write_text("\n".join(test) + "\n")
    rng = np.random.default_rng([spec.seed, 1])
    xyz, rgb, _ = sample_seed_points(
        scene, c2ws[0::2], intrinsics, spec.width, spec.height, spec.num_points, spec.point_noise, rng
    )
    write_colmap_text_model(folder / "sparse" / "0", spec.width, spec.height, intrinsics, names, c2ws, xyz, rgb)
    (folder / "demo.json").write_text(json.dumps({"version": DEMO_VERSION, **spec_values(spec)}, indent=2))
    return folder


def ensure_demo_scene(spec: DemoSceneSpec, cache_dir: Path | None = None) -> Path:
    """The cached demo scene folder for ``spec``, generated atomically on first use."""
    spec.validate()
    root = Path(cache_dir) if cache_dir is not None else default_cache_dir() / "demo"
    final = root / spec.key()
    if (final / "demo.json").is_file():
        return final
    try:
        root.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(dir=root, prefix=f".{spec.key()}."))
    except OSError as exc:
        raise DataParserError(
            f"cannot write the demo scene into {root} ({exc.strerror}): set {CACHE_ENV} to a writable folder"
        ) from exc
    try:
        generate_demo_scene(spec, tmp / "scene")
        try:
            os.rename(tmp / "scene", final)
        except OSError:
            if not (final / "demo.json").is_file():  # not a concurrent writer finishing first: a real error
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return final


@dataclass
class DemoDataParserConfig(DemoSceneSpec, Spars3rDataParserConfig):
    """The generated demo scene (``--data demo``); ``data`` is ignored and set to the cached scene folder.

    The scene's fields (seed, width, height, num_cameras, num_points, point_noise) are :class:`DemoSceneSpec`'s; as
    the first base it puts them after the SPARS3R parser's fields, where the command line and ``config.yml`` list them.
    """

    data: Path = Path("demo")
    demo_cache_dir: Path | None = None
    """Where generated scenes go; None: ``$KC_SPLATFACTO_CACHE/demo`` (``~/.cache/kc_splatfacto/demo``)."""

    def spec(self) -> DemoSceneSpec:
        """The scene this config generates, as a bare :class:`DemoSceneSpec`."""
        return DemoSceneSpec(**spec_values(self))

    def setup(self) -> Spars3rDataParser:
        folder = ensure_demo_scene(self.spec(), self.demo_cache_dir)
        parser_config = Spars3rDataParserConfig(
            data=folder,
            downscale_factor=self.downscale_factor,
            orientation_method=self.orientation_method,
            center_method=self.center_method,
            auto_scale_poses=self.auto_scale_poses,
            cache_dir=self.cache_dir,
            images_path=self.images_path,
            colmap_path=self.colmap_path,
            load_3d_points=self.load_3d_points,
            masks_path=self.masks_path,
        )
        return Spars3rDataParser(parser_config)


def _spec():
    return DataParserSpecification(
        config=DemoDataParserConfig(),
        description="generated demo scene (boxes and planes, 24 views, 12/12 split), cached on first use",
    )


demo_dataparser = _spec()
