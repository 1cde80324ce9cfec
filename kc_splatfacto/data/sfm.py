"""Camera poses for a folder of photos: COLMAP structure-from-motion through pycolmap, on the CPU.

``process_images(config)`` (``kc-process-data images --data PHOTOS --output-dir SCENE``) writes the layout the
``colmap`` dataparser reads::

    <scene>/images/          the registered photos (undistorted when the camera model has distortion)
    <scene>/sparse/0/        the PINHOLE model: cameras, images, points3D (.bin)
    <scene>/colmap/          database.db and the mapper's own model (distorted, every point) in sparse/0

and with ``num_train`` a SPARS3R-style sparse split as well (the ``spars3r`` dataparser's layout)::

    <scene>/train_list.txt   ``num_train`` views spread evenly over the registered views that are not test views
    <scene>/test_list.txt    every ``test_every``-th registered view in name order (LLFF's protocol)

in which case points3D holds only points triangulated from the train views with every pose and intrinsic held
fixed (the poses themselves come from all registered views, as SPARS3R's).

Stages: feature extraction (SIFT), matching (exhaustive, sequential or GPS-spatial), incremental mapping (retried
with other focal-length priors when no initial pair is found), the optional split with its triangulation,
undistortion to PINHOLE. Each failure a user can act on is a :class:`ProcessDataError` of one line.
"""

from __future__ import annotations

import contextlib
import math
import os
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from PIL import Image, UnidentifiedImageError

from kc_splatfacto.data.colmap_files import import_pycolmap
from kc_splatfacto.data.images import IMAGE_EXTENSIONS
from kc_splatfacto.errors import Interrupted, UserError
from kc_splatfacto.settings import choice_violations, integer, range_violations, setting

#: COLMAP's image readers do not decode EXR; everything else in IMAGE_EXTENSIONS they do.
SFM_IMAGE_EXTENSIONS = tuple(ext for ext in IMAGE_EXTENSIONS if ext != ".exr")
#: fewer photos than this cannot give a model worth training on (two views triangulate, a third checks)
MIN_IMAGES = 3
#: ``auto`` matching: every pair up to this many photos (n^2/2 pairs), sequential neighbours beyond
EXHAUSTIVE_MAX_IMAGES = 100
#: test views are every 8th registered view in name order (LLFF's and SPARS3R's protocol)
TEST_EVERY = 8
#: COLMAP's focal guess without EXIF (ImageReaderOptions.default_focal_length_factor) times the longer side
DEFAULT_FOCAL_FACTOR = 1.2
#: the fallback focal prior: a wide-angle lens (about 71 degrees across the longer side, a phone's main camera)
WIDE_FOCAL_FACTOR = 0.7
#: initial-pair thresholds of the last attempt (COLMAP's defaults: 16 degrees, 100 inliers)
RELAXED_INIT_MIN_TRI_ANGLE = 4.0
#: pycolmap's mapper keeps its random seed in a C++ int: 0 .. 2**31 - 1
SEED_MAX = 2**31 - 1
#: the smallest longer side SIFT is given (below it too few features survive to match)
MIN_IMAGE_SIZE = 64
RELAXED_INIT_MIN_NUM_INLIERS = 50

MatchingMethod = Literal["auto", "exhaustive", "sequential", "spatial"]
CameraModel = Literal["SIMPLE_RADIAL", "OPENCV", "RADIAL", "SIMPLE_PINHOLE", "PINHOLE"]
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")


class ProcessDataError(UserError, ValueError):
    """Photos that cannot become a scene, or a flag that does not fit them; the message says which and why."""


@dataclass
class ProcessImagesConfig:
    """``kc-process-data images``: camera poses and seed points for a folder of photos (COLMAP through pycolmap)."""

    data: Path
    """folder of photos (jpg, png, tif, bmp, webp; sub-folders are ignored)"""
    output_dir: Path
    """scene folder to write (images/, sparse/0/, colmap/; train_list.txt and test_list.txt with --num-train)"""
    matching_method: MatchingMethod = "auto"
    """feature matching: exhaustive (every pair), sequential (neighbours in name order: video frames), spatial
    (GPS from EXIF); auto is exhaustive up to 100 photos, sequential beyond"""
    camera_model: CameraModel = "SIMPLE_RADIAL"
    """COLMAP camera model (one camera shared when all photos have one size); distorted ones are undistorted to
    PINHOLE"""
    num_train: int | None = setting(None, integer(1, optional=True))
    """a SPARS3R-style sparse split: this many train views, every 8th view for test, seed points from train only"""
    max_image_size: int = setting(3200, integer(MIN_IMAGE_SIZE))
    """longer side of the image SIFT sees (larger photos are downscaled for extraction only)"""
    seed: int = setting(0, integer(0, SEED_MAX))
    """random seed of COLMAP's RANSAC and mapper (results are repeatable up to multi-threading order)"""
    overwrite: bool = False
    """replace images/, sparse/ and colmap/ of an existing output folder"""
    verbose: bool = False
    """show COLMAP's own log"""


@dataclass
class MappingAttempt:
    """One incremental-mapping try: its focal prior and initial-pair thresholds, and what it registered."""

    label: str
    focal_factor: float | None
    relaxed_init: bool
    registered: int = 0


@dataclass
class ProcessResult:
    """What ``process_images`` wrote and found.

    Attributes:
        scene: the scene folder. registered: names of the registered photos (name order).
        unregistered: photos left out of the model. attempts: the mapping attempts made, in order.
        train, test: the split (empty without ``num_train``). num_points: points in ``sparse/0``.
        stage_seconds: wall-clock seconds per stage.
    """

    scene: Path
    registered: list[str]
    unregistered: list[str]
    attempts: list[MappingAttempt]
    train: list[str] = field(default_factory=list)
    test: list[str] = field(default_factory=list)
    num_points: int = 0
    camera_model: str = ""
    stage_seconds: dict[str, float] = field(default_factory=dict)


def list_photos(folder: Path) -> list[str]:
    """Names of the photos directly in ``folder`` (name order); an error naming the folder when it has too few."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ProcessDataError(f"--data {folder} is not a folder: pass the folder that holds the photos")
    names = sorted(
        p.name for p in folder.iterdir()
        if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in SFM_IMAGE_EXTENSIONS
    )
    if len(names) < MIN_IMAGES:
        raise ProcessDataError(
            f"--data {folder} holds {len(names)} photo(s) ({', '.join(SFM_IMAGE_EXTENSIONS)}); structure from motion "
            f"needs at least {MIN_IMAGES} overlapping photos of the scene{_photos_below(folder)}"
        )
    return names


def _photos_below(folder: Path) -> str:
    """A hint naming the subfolders of ``folder`` that hold photos (photos are read from ``--data`` itself only)."""
    found = []
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith(".")):
        count = sum(1 for f in sub.rglob("*") if f.is_file() and f.suffix.lower() in SFM_IMAGE_EXTENSIONS)
        if count:
            found.append(f"{sub} ({count})")
    if not found:
        return ""
    return f"; photos were found in subfolders: {', '.join(found[:3])}: pass that folder as --data"


def check_photos(folder: Path, names: list[str]) -> None:
    """An error naming the file for a photo that does not decode completely (a truncated JPEG: OpenCV, and so
    COLMAP's reader, fills the missing part with grey without a word) and for two byte-identical photos (one could
    become a training view and its twin a test view: a test view seen in training)."""
    import hashlib

    from kc_splatfacto.data.base import DataParserError
    from kc_splatfacto.data.images import check_complete

    seen: dict[str, str] = {}
    for name in names:
        path = folder / name
        try:
            check_complete(path)
        except DataParserError as exc:
            raise ProcessDataError(f"{exc}; kc-process-data reads every photo in --data {folder}") from exc
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        if digest in seen:
            raise ProcessDataError(
                f"photos {folder / seen[digest]} and {path} are the same file (byte for byte): remove one, or the "
                "same view could be a training and a test view"
            )
        seen[digest] = name


def choose_matching(method: str, num_images: int) -> str:
    """The matcher ``auto`` stands for: exhaustive for small sets, sequential for large ones."""
    if method != "auto":
        return method
    return "exhaustive" if num_images <= EXHAUSTIVE_MAX_IMAGES else "sequential"


def sparse_split(names: list[str], num_train: int, test_every: int = TEST_EVERY) -> tuple[list[str], list[str]]:
    """SPARS3R's split of the registered views: every ``test_every``-th name (from the first) is a test view, and
    ``num_train`` train views are spread evenly over the others (first and last included); the rest are unused.

    Args:
        names: registered view names. num_train: >= 1.
    Returns:
        (train, test), each in name order.
    """
    names = sorted(names)
    test = names[::test_every]
    rest = [n for i, n in enumerate(names) if i % test_every != 0]
    if num_train < 1:
        raise ProcessDataError(f"--num-train must be at least 1, got {num_train}")
    if num_train > len(rest):
        raise ProcessDataError(
            f"--num-train {num_train} is more than the {len(rest)} registered views that are not test views "
            f"({len(names)} registered, every {test_every}th is a test view): lower --num-train or add photos"
        )
    picks = np.unique(np.round(np.linspace(0, len(rest) - 1, num_train)).astype(int))
    return [rest[i] for i in picks], test


@contextlib.contextmanager
def colmap_log(verbose: bool) -> Iterator[None]:
    """COLMAP's glog quiet unless ``verbose`` (its errors too: the ones a user can act on become our one line);
    the previous level restored afterwards."""
    import pycolmap

    previous = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = previous if verbose else max(previous, 3)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = previous


def photo_sizes(photos: Path, names: list[str]) -> set[tuple[int, int]]:
    """The distinct (width, height) of the photos, from their headers."""
    sizes = set()
    for name in names:
        try:
            with Image.open(photos / name) as image:
                sizes.add(image.size)
        except (OSError, UnidentifiedImageError) as exc:
            raise ProcessDataError(f"photo {photos / name} is not an image that can be read ({exc}): remove it") from None
    return sizes


def extract_features(database: Path, photos: Path, names: list[str], config: ProcessImagesConfig) -> None:
    """SIFT features of ``names`` into a fresh ``database``: one shared camera when every photo has one size (a
    single capture, as ns-process-data assumes), else COLMAP's AUTO (a camera per size and EXIF, or per photo)."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = config.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = config.max_image_size
    # one extraction thread per core: SIFT's RAM is per thread, and the host has few cores
    extraction.num_threads = max(1, min(os.cpu_count() or 1, 4))
    mode = pycolmap.CameraMode.SINGLE if len(photo_sizes(photos, names)) == 1 else pycolmap.CameraMode.AUTO
    pycolmap.extract_features(database, photos, image_names=names, camera_mode=mode,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)


def match_features(database: Path, method: str, num_images: int) -> None:
    """Match and geometrically verify image pairs with the chosen pairing (names the fix when spatial cannot run)."""
    import pycolmap

    if method == "exhaustive":
        pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
    elif method == "sequential":
        # neighbours in name order; vocabulary-tree loop detection is off (its tree is a separate download)
        pycolmap.match_sequential(database, device=pycolmap.Device.cpu)
    elif method == "spatial":
        db = pycolmap.Database.open(database)
        try:
            with_gps = db.num_pose_priors()
        finally:
            db.close()
        if with_gps == 0:
            raise ProcessDataError(
                f"--matching-method spatial needs GPS positions in the photos' EXIF and none of the {num_images} "
                "photos has one: use --matching-method sequential (video frames) or exhaustive"
            )
        pycolmap.match_spatial(database, device=pycolmap.Device.cpu)
    else:
        raise ProcessDataError(f"unknown --matching-method {method}: use auto, exhaustive, sequential or spatial")


def verified_pairs(database: Path) -> int:
    """Image pairs with a verified two-view geometry in ``database``."""
    import pycolmap

    db = pycolmap.Database.open(database)
    try:
        return int(db.num_verified_image_pairs())
    finally:
        db.close()


def mapping_attempts(database: Path) -> list[MappingAttempt]:
    """The focal priors to try, in order: the EXIF focal when the photos have one, COLMAP's default guess, a
    wide-angle prior, and last the first prior again with relaxed initial-pair thresholds."""
    import pycolmap

    db = pycolmap.Database.open(database)
    try:
        has_exif = any(camera.has_prior_focal_length for camera in db.read_all_cameras())
    finally:
        db.close()
    attempts = [MappingAttempt("the EXIF focal length", None, False)] if has_exif else []
    attempts.append(MappingAttempt(f"{DEFAULT_FOCAL_FACTOR} x the longer side (COLMAP's guess without EXIF)",
                                   DEFAULT_FOCAL_FACTOR, False))
    attempts.append(MappingAttempt(f"{WIDE_FOCAL_FACTOR} x the longer side (a wide-angle prior)",
                                   WIDE_FOCAL_FACTOR, False))
    first = attempts[0]
    attempts.append(MappingAttempt(
        f"{first.label} with a relaxed initial pair ({RELAXED_INIT_MIN_TRI_ANGLE:g} deg, "
        f"{RELAXED_INIT_MIN_NUM_INLIERS} inliers)", first.focal_factor, True))
    return attempts


def set_focal_prior(database: Path, factor: float | None, exif_focals: dict[int, float]) -> None:
    """Every camera's focal length: ``factor`` x its longer side, or (None) the EXIF value it was read with."""
    import pycolmap

    db = pycolmap.Database.open(database)
    try:
        for camera in db.read_all_cameras():
            focal = exif_focals[camera.camera_id] if factor is None else factor * max(camera.width, camera.height)
            params = np.array(camera.params, dtype=np.float64)
            params[list(camera.focal_length_idxs())] = focal
            camera.params = params  # type: ignore[assignment]  # pycolmap's stub says Sequence; it takes arrays
            db.update_camera(camera)
    finally:
        db.close()


def _focal_of_cameras(database: Path) -> dict[int, float]:
    import pycolmap

    db = pycolmap.Database.open(database)
    try:
        return {c.camera_id: float(np.mean([c.params[i] for i in c.focal_length_idxs()])) for c in db.read_all_cameras()}
    finally:
        db.close()


def run_mapping(database: Path, photos: Path, model_root: Path, names: list[str], config: ProcessImagesConfig,
                progress: Callable[[str], None]):
    """Incremental mapping, retried with the next focal prior while no model registers every photo.

    Returns:
        (the reconstruction registering most photos, the attempts made).
    Raises:
        ProcessDataError when no attempt finds an initial pair (the message lists the priors tried).
    """
    import pycolmap

    exif_focals = _focal_of_cameras(database)
    attempts = mapping_attempts(database)
    best, made = None, []
    for number, attempt in enumerate(attempts):
        made.append(attempt)
        if number > 0 or attempt.focal_factor is not None:
            set_focal_prior(database, attempt.focal_factor, exif_focals)
        options = pycolmap.IncrementalPipelineOptions()
        options.random_seed = config.seed
        if attempt.relaxed_init:
            options.mapper.init_min_tri_angle = RELAXED_INIT_MIN_TRI_ANGLE
            options.mapper.init_min_num_inliers = RELAXED_INIT_MIN_NUM_INLIERS
        out = model_root / f"attempt{number}"
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        count = [0]

        every = max(1, len(names) // 10)

        def registered(count: list[int] = count, every: int = every) -> None:
            count[0] += 1  # called before each image after the initial pair: count + 2 are in the model
            if (count[0] + 2) % every == 0 or count[0] + 2 == len(names):
                progress(f"      registering: {count[0] + 2}/{len(names)}")

        progress(f"  mapping with the focal prior {attempt.label}")
        models = pycolmap.incremental_mapping(database, photos, out, options=options,
                                              next_image_callback=registered)
        if models:
            model = max(models.values(), key=lambda r: r.num_reg_images())
            attempt.registered = model.num_reg_images()
            if best is None or attempt.registered > best.num_reg_images():
                best = model
            if attempt.registered == len(names):
                break
        else:
            progress("  no initial image pair")
    if best is None:
        pairs = verified_pairs(database)
        raise ProcessDataError(
            f"no initial image pair found in {photos} ({pairs} verified image pairs among {len(names)} photos); "
            f"tried the focal priors {'; '.join(a.label for a in made)}: the photos need more overlap "
            "(neighbouring views sharing most of their content) or more texture"
        )
    return best, made


def check_registered(model, names: list[str], photos: Path) -> list[str]:
    """Names of ``names`` not in ``model``; an error when fewer than MIN_IMAGES registered (listing the rest)."""
    registered = {image.name for image in model.images.values() if image.has_pose}
    missing = [n for n in names if n not in registered]
    if len(registered) < MIN_IMAGES:
        raise ProcessDataError(
            f"only {len(registered)} of {len(names)} photos in {photos} registered (not: {', '.join(missing)}): "
            "the photos need more overlap or texture"
        )
    return missing


def triangulate_train_only(model, train: list[str], database: Path, photos: Path, work: Path):
    """``model`` with its points replaced by points triangulated from the ``train`` views alone, every pose and
    intrinsic held fixed (SPARS3R's seed points); the other views keep their poses and see no point."""
    import pycolmap

    train_only = pycolmap.Reconstruction(model)
    keep = set(train)
    for image in list(train_only.images.values()):
        if image.has_pose and image.name not in keep:
            train_only.deregister_frame(image.frame_id)
    work.mkdir(parents=True, exist_ok=True)
    triangulated = pycolmap.triangulate_points(train_only, database, photos, work, clear_points=True,
                                               refine_intrinsics=False)
    result = pycolmap.Reconstruction(model)
    for point_id in list(result.point3D_ids()):
        result.delete_point3D(point_id)
    names = {image_id: image.name for image_id, image in result.images.items()}
    for point in triangulated.points3D.values():
        for element in point.track.elements:
            if names.get(element.image_id) != triangulated.images[element.image_id].name:
                raise RuntimeError("triangulate_points renumbered the images")  # a pycolmap change: a bug here
        result.add_point3D(point.xyz, point.track, point.color)
    return result


def write_scene(model, photos: Path, scene: Path, work: Path) -> str:
    """``scene/images`` and ``scene/sparse/0`` from ``model``: undistorted to PINHOLE when its cameras have
    distortion, else the photos copied as they are. Returns the written camera model's name."""
    import pycolmap

    distorted_dir = work / "to_undistort"
    shutil.rmtree(distorted_dir, ignore_errors=True)
    distorted_dir.mkdir(parents=True)
    model.write(distorted_dir)
    names = sorted(image.name for image in model.images.values() if image.has_pose)
    models = {camera.model.name for camera in model.cameras.values()}
    if models <= set(PINHOLE_MODELS):
        (scene / "images").mkdir(parents=True)
        for name in names:
            shutil.copy2(photos / name, scene / "images" / name)
        (scene / "sparse" / "0").mkdir(parents=True)
        model.write(scene / "sparse" / "0")
        shutil.rmtree(distorted_dir, ignore_errors=True)
        return "/".join(sorted(models))
    undistorted = work / "undistorted"
    shutil.rmtree(undistorted, ignore_errors=True)
    pycolmap.undistort_images(undistorted, distorted_dir, photos, image_names=names, output_type="COLMAP")
    shutil.move(str(undistorted / "images"), str(scene / "images"))
    (scene / "sparse").mkdir(parents=True)
    shutil.move(str(undistorted / "sparse"), str(scene / "sparse" / "0"))
    shutil.rmtree(undistorted, ignore_errors=True)
    shutil.rmtree(distorted_dir, ignore_errors=True)
    return "PINHOLE"


SCENE_PARTS = ("images", "sparse", "colmap", "train_list.txt", "test_list.txt")
"""what kc-process-data writes in --output-dir (and replaces there with --overwrite)"""


def prepare_output(scene: Path, photos: Path, overwrite: bool) -> None:
    """An error when ``scene`` already holds a scene (unless ``overwrite``) or is the photo folder itself. Nothing is
    deleted here: the new scene is built beside it and replaces it only once complete (:func:`publish_scene`)."""
    scene = Path(scene)
    if scene.resolve() == Path(photos).resolve() or (scene / "images").resolve() == Path(photos).resolve():
        raise ProcessDataError(
            f"--output-dir {scene} would write over the photos in {photos}: choose another output folder"
        )
    if scene.exists() and not scene.is_dir():
        raise ProcessDataError(f"--output-dir {scene} is a file, not a folder: choose a folder for the scene")
    existing = [name for name in ("images", "sparse", "colmap") if (scene / name).exists()]
    if existing and not overwrite:
        raise ProcessDataError(
            f"--output-dir {scene} already holds {', '.join(existing)}: choose an empty folder or pass --overwrite"
        )


def staging_folder(scene: Path) -> Path:
    """Where a scene is built before it replaces ``scene``'s parts: a hidden sibling (same file system, so the
    replacement is a rename), emptied first when an earlier attempt left it."""
    staging = scene.parent / f".{scene.name}.kc-process-data.partial"
    shutil.rmtree(staging, ignore_errors=True)
    try:
        staging.mkdir(parents=True)
    except OSError as exc:
        raise ProcessDataError(f"--output-dir {scene}: cannot write in {scene.parent} ({exc.strerror}): choose a "
                               "folder you can write to") from exc
    return staging


def publish_scene(staging: Path, scene: Path) -> None:
    """Replace ``scene``'s parts by the complete new ones in ``staging``: the old parts are moved into the staging
    folder first (deleted with it), so an error here leaves the old scene or the new one, never neither."""
    scene.mkdir(parents=True, exist_ok=True)
    replaced = staging / "replaced"
    replaced.mkdir()
    for name in SCENE_PARTS:
        if (scene / name).exists():
            (scene / name).replace(replaced / name)
    try:
        for name in SCENE_PARTS:
            if (staging / name).exists():
                (staging / name).replace(scene / name)
    except BaseException:  # Ctrl-C too: the old parts would be deleted with the staging folder
        for name in SCENE_PARTS:
            if (replaced / name).exists() and not (scene / name).exists():
                (replaced / name).replace(scene / name)
        raise


def process_images(config: ProcessImagesConfig, progress: Callable[[str], None] = print) -> ProcessResult:
    """Photos -> a COLMAP scene (see the module docstring); ``progress`` gets one line per stage and step.

    A Ctrl-C at any stage leaves ``output_dir`` as it was (an :class:`~kc_splatfacto.errors.Interrupted` saying so)."""
    scene = Path(config.output_dir)
    had_scene = _holds_files(scene)
    try:
        return _process_images(config, progress)
    except KeyboardInterrupt:
        kept = " (the scene already there is as it was)" if had_scene else ""
        raise Interrupted(f"nothing was written to --output-dir {scene}{kept}; run the same command to start "
                          "again") from None


def _holds_files(folder: Path) -> bool:
    try:
        return folder.is_dir() and any(folder.iterdir())
    except OSError:  # unreadable: prepare_output says so
        return False


def _process_images(config: ProcessImagesConfig, progress: Callable[[str], None]) -> ProcessResult:
    photos = Path(config.data)
    scene = Path(config.output_dir)
    check_config(config)
    names = list_photos(photos)
    if config.num_train is not None and config.num_train >= len(names):
        raise ProcessDataError(
            f"--num-train {config.num_train} leaves no test view among the {len(names)} photos in {photos}: "
            f"every {TEST_EVERY}th view is a test view, so at most {len(names) - math.ceil(len(names) / TEST_EVERY)} "
            "can train"
        )
    check_photos(photos, names)
    prepare_output(scene, photos, config.overwrite)
    created = missing_folders(scene.parent)
    staging = staging_folder(scene)
    published = False
    try:
        result = _process_into(staging, photos, names, config, progress)
        publish_scene(staging, scene)
        published = True
    finally:  # also on an error or Ctrl-C: the old scene untouched, nothing half-written left behind
        shutil.rmtree(staging, ignore_errors=True)
        if not published:
            remove_empty_folders(created)
    result.scene = scene
    return result


def check_config(config: ProcessImagesConfig) -> None:
    """Every value of ``config`` within its choices and its declared range (``setting`` beside each field), checked
    before any photo is read: a :class:`ProcessDataError` naming the flag, not pycolmap's TypeError later."""
    for violation in (*choice_violations(config), *range_violations(config)):
        flag = "--" + violation.name.replace("_", "-")
        raise ProcessDataError(f"{flag} {violation.value!r} is not allowed: {flag} must be {violation.allowed}")


def missing_folders(folder: Path) -> list[Path]:
    """``folder`` and those of its parents that do not exist yet, deepest first (what a ``mkdir(parents=True)``
    would create)."""
    missing = []
    for candidate in (Path(folder), *Path(folder).parents):
        if candidate.exists():
            break
        missing.append(candidate)
    return missing


def remove_empty_folders(folders: list[Path]) -> None:
    """Remove ``folders`` (deepest first) that are empty: the ones a failed run created for nothing."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:  # not empty (someone else wrote there) or already gone: leave it
            break


def _process_into(scene: Path, photos: Path, names: list[str], config: ProcessImagesConfig,
                  progress: Callable[[str], None]) -> ProcessResult:
    """The stages of :func:`process_images`, writing the scene into ``scene`` (the staging folder)."""
    pycolmap = import_pycolmap()

    work = scene / "colmap"
    work.mkdir()
    database = work / "database.db"
    method = choose_matching(config.matching_method, len(names))
    pycolmap.set_random_seed(config.seed)
    seconds: dict[str, float] = {}
    stages = 5 if config.num_train is not None else 4

    @contextlib.contextmanager
    def stage(number: int, key: str, text: str) -> Iterator[None]:
        progress(f"[{number}/{stages}] {text}")
        start = time.perf_counter()
        yield
        seconds[key] = time.perf_counter() - start
        progress(f"      {key} done in {seconds[key]:.1f} s")

    with colmap_log(config.verbose):
        with stage(1, "features", f"extracting SIFT features from {len(names)} photos"):
            extract_features(database, photos, names, config)
        pairs_text = f"{len(names) * (len(names) - 1) // 2} pairs" if method == "exhaustive" else "neighbours"
        with stage(2, "matching", f"matching features ({method}, {pairs_text})"):
            match_features(database, method, len(names))
        with stage(3, "mapping", "incremental mapping"):
            model, attempts = run_mapping(database, photos, work / "attempts", names, config, progress)
            shutil.rmtree(work / "attempts", ignore_errors=True)
            (work / "sparse" / "0").mkdir(parents=True)
            model.write(work / "sparse" / "0")  # the mapper's own model, every point, before any split
            unregistered = check_registered(model, names, photos)
            if unregistered:
                progress(f"      {len(unregistered)} of {len(names)} photos did not register and are left out: "
                         f"{', '.join(unregistered)}")
        registered = sorted(image.name for image in model.images.values() if image.has_pose)
        train: list[str] = []
        test: list[str] = []
        if config.num_train is not None:
            with stage(4, "split", f"sparse split: {config.num_train} train views, every {TEST_EVERY}th for test, "
                                   "seed points from the train views (poses fixed)"):
                train, test = sparse_split(registered, config.num_train)
                model = triangulate_train_only(model, train, database, photos, work / "train_points")
        with stage(stages, "undistortion", "writing images/ and sparse/0 (undistorted to PINHOLE when needed)"):
            camera_model = write_scene(model, photos, scene, work)
    if config.num_train is not None:
        (scene / "train_list.txt").write_text("".join(f"{n}\n" for n in train))
        (scene / "test_list.txt").write_text("".join(f"{n}\n" for n in test))
    return ProcessResult(scene=scene, registered=registered, unregistered=unregistered, attempts=attempts,
                         train=train, test=test, num_points=model.num_points3D(), camera_model=camera_model,
                         stage_seconds=seconds)
