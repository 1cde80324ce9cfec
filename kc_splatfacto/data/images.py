"""Image files: reading (OpenCV), header sizes, and the cached downscaled / undistorted copies.

Derived images are written atomically (temp file + rename) and reused when present, never behind a prompt.
Pixel convention: pixel ``(i, j)`` covers ``[j, j+1) x [i, i+1)``, centres at +0.5 (COLMAP's and gsplat's), so a
resize by ``w_new / w`` scales ``fx`` and ``cx`` by exactly that ratio.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import stat
import warnings
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from kc_splatfacto.atomic import atomic_write_bytes, atomic_write_text
from kc_splatfacto.data.base import CACHE_ENV, READ_ONLY_DATA_ENV, DataParserError, default_cache_dir

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".exr")
# Folder under the user cache for derived images of scenes whose own folder is read-only.
DERIVED_CACHE_SUBDIR = "derived"


def read_image(path: str | Path) -> np.ndarray:
    """Decode an image file to RGB(A).

    Returns:
        [H, W, 3] or [H, W, 4] uint8 (16-bit files are rounded to 8 bits; float files must hold finite values in
        [0, 1] or [0, 255], their range decides the scale, and are quantized).
    """
    path = Path(path)
    if not path.is_file():
        raise DataParserError(f"image file {path} does not exist: check the scene's image folder")
    header_size(path)  # a decompression bomb is refused before OpenCV allocates it
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        raise DataParserError(f"image file {path} is corrupt or not an image OpenCV can read: re-export or remove it")
    check_complete(path)
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)
    elif image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    else:
        raise DataParserError(f"image file {path} has {image.shape[2]} channels: expected gray, RGB or RGBA")
    return to_uint8(image, path)


def _bomb_error(path: Path, exc: Exception) -> DataParserError:
    return DataParserError(
        f"image file {path} is refused as a decompression bomb ({exc}): an image that large cannot be a training "
        "view; downscale it first (or check that the file is what it claims to be)"
    )


def header_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from the file's header through Pillow (None for formats Pillow does not know); a
    :class:`DataParserError` for a decompression bomb (Pillow's limit)."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # the error threshold is what counts
            with Image.open(path) as handle:
                return int(handle.size[0]), int(handle.size[1])
    except Image.DecompressionBombError as exc:
        raise _bomb_error(path, exc) from exc
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError):
        return None


def image_has_alpha(path: Path) -> bool:
    """Whether the image file holds an alpha channel (or a transparent palette entry), from its header."""
    try:
        with Image.open(path) as handle:
            return handle.mode in ("RGBA", "LA", "PA", "RGBa", "La") or "transparency" in handle.info
    except Exception:  # noqa: BLE001  a format Pillow does not know (EXR): OpenCV's channel count decides on read
        return False


def check_complete(path: Path) -> None:
    """An error naming ``path`` when its image data ends early or is damaged.

    OpenCV decodes a truncated JPEG with a flat grey lower part and only prints a libjpeg warning without the file
    name; Pillow's full decode raises instead. Formats Pillow does not know (e.g. EXR) are left to OpenCV.
    """
    try:
        handle = Image.open(path)
    except UnidentifiedImageError:
        return
    except Image.DecompressionBombError as exc:
        raise _bomb_error(path, exc) from exc
    except OSError as exc:
        raise DataParserError(f"image file {path} cannot be opened ({exc}): re-export or remove it") from exc
    try:
        with handle:
            handle.load()
    except (OSError, SyntaxError, ValueError) as exc:  # Pillow's "image file is truncated", broken data streams
        raise DataParserError(
            f"image file {path} does not decode completely ({exc}): the file is truncated or damaged; "
            "copy it again or remove it from the scene"
        ) from exc


def to_uint8(image: np.ndarray, path: str | Path = "<array>") -> np.ndarray:
    """uint8 / uint16 / float image -> uint8; non-finite float pixels are an error naming ``path``."""
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:
        return np.round(image.astype(np.float32) / 257.0).astype(np.uint8)
    if np.issubdtype(image.dtype, np.floating):
        bad = ~np.isfinite(image)
        if bad.any():
            raise DataParserError(
                f"image {path} has {int(bad.sum())} NaN/inf values: fix or re-export the file "
                "(expected values in [0,1])"
            )
        low, high = float(image.min()), float(image.max())
        if low >= 0.0 and high <= 1.0:
            return np.round(image * 255.0).astype(np.uint8)
        if low >= 0.0 and high <= 255.0:  # a float file holding 8-bit values: its real range, not clipped to white
            return np.round(image).astype(np.uint8)
        raise DataParserError(
            f"image {path} is a float image with values in [{low:g}, {high:g}], neither 0..1 nor 0..255: rescale it "
            "to one of those ranges (or export it as 8/16-bit)"
        )
    raise DataParserError(f"image {path} has unsupported pixel type {image.dtype}: expected 8/16-bit or float")


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file from its header (no full decode); a clear error if unreadable."""
    path = Path(path)
    if not path.is_file():
        raise DataParserError(f"image file {path} does not exist: check the scene's image folder and split lists")
    size = header_size(path)
    if size is not None:
        return size
    image = read_image(path)  # PIL cannot parse every format OpenCV reads (e.g. EXR): decode fully
    return int(image.shape[1]), int(image.shape[0])


def write_image_atomic(path: Path, image: np.ndarray) -> None:
    """Write an RGB(A) uint8 image with OpenCV via a temp file + rename (lossless PNG unless the suffix says JPEG)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if image.ndim == 3 and image.shape[2] == 4:
        bgr = cv2.cvtColor(image, cv2.COLOR_RGBA2BGRA)
    elif image.ndim == 3:
        bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    else:
        bgr = image
    suffix = path.suffix.lower() or ".png"
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if suffix in (".jpg", ".jpeg") else []
    ok, encoded = cv2.imencode(suffix, bgr, params)
    if not ok:
        raise DataParserError(f"OpenCV could not encode {path} (suffix {suffix})")
    atomic_write_bytes(path, encoded.tobytes())


def read_only_in_intent(folder: Path) -> bool:
    """Whether ``folder`` is under one of the folders ``$KC_SPLATFACTO_READ_ONLY_DATA`` names."""
    entries = [e for e in os.environ.get(READ_ONLY_DATA_ENV, "").split(os.pathsep) if e.strip()]
    if not entries:
        return False
    resolved = Path(folder).resolve()
    return any(resolved.is_relative_to(Path(entry).expanduser().resolve()) for entry in entries)


def folder_is_writable(folder: Path) -> bool:
    """Whether derived files may go into ``folder``: it allows writes by mode bits and by the OS, and is not under a
    folder ``$KC_SPLATFACTO_READ_ONLY_DATA`` names.

    Mode bits are checked too because a read-only shared scene stays read-only in intent even for root.
    """
    if read_only_in_intent(folder):
        return False
    try:
        mode = folder.stat().st_mode
    except OSError:
        return False
    return bool(mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH)) and os.access(folder, os.W_OK)


def derived_root(images_dir: Path, cache_dir: Path | None) -> Path:
    """Folder that holds ``<images>_N/`` style derived image folders for a scene.

    ``cache_dir`` given: a per-scene subfolder of it. Otherwise the scene folder itself when writable, else a
    per-scene subfolder of the user cache.
    """
    scene = images_dir.resolve().parent
    if cache_dir is None and folder_is_writable(scene):
        return scene
    base = Path(cache_dir) if cache_dir is not None else default_cache_dir() / DERIVED_CACHE_SUBDIR
    digest = hashlib.sha1(str(scene).encode()).hexdigest()[:10]
    return base / f"{scene.name}-{digest}"


#: Hidden folder, inside each derived folder, holding one JSON per derived image: the source's size and mtime.
SOURCE_RECORDS = ".sources"


def _source_stamp(source: Path) -> dict:
    info = Path(source).stat()
    return {"size": info.st_size, "mtime_ns": info.st_mtime_ns}


def _record_path(target: Path, derived_folder: Path) -> Path:
    return derived_folder / SOURCE_RECORDS / (str(target.relative_to(derived_folder)) + ".json")


def derived_is_fresh(target: Path, source: Path, derived_folder: Path) -> bool:
    """Whether the derived image ``target`` (inside ``derived_folder``) was made from ``source`` as it is now.

    Written by this project: the source's size and mtime recorded beside it must match. Shipped with the scene (no
    record): fresh unless the source is newer than it.
    """
    if not target.is_file():
        return False
    record = _record_path(target, derived_folder)
    if record.is_file():
        try:
            return json.loads(record.read_text()) == _source_stamp(source)
        except (OSError, ValueError):
            return False
    return target.stat().st_mtime_ns >= Path(source).stat().st_mtime_ns


def write_derived(target: Path, image: np.ndarray, source: Path, derived_folder: Path) -> None:
    """Write a derived image and record its source's size and mtime (see :func:`derived_is_fresh`); a full disk is
    a :class:`DataParserError` naming the file (the atomic write leaves no partial file)."""
    try:
        write_image_atomic(target, image)
        atomic_write_text(_record_path(target, derived_folder), json.dumps(_source_stamp(source)))
    except OSError as exc:
        if exc.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EPERM):
            raise
        raise DataParserError(
            f"could not write the derived image {target} ({exc.strerror or exc}): free space there, or set "
            f"cache_dir (or ${CACHE_ENV}) to a folder with room; nothing partial was left"
        ) from exc


def resized_size(width: int, height: int, factor: int) -> tuple[int, int]:
    """Size after an integer downscale: floor division, as nerfstudio's ``rescale_output_resolution``."""
    new_w, new_h = width // factor, height // factor
    if new_w < 1 or new_h < 1:
        raise DataParserError(f"downscale_factor {factor} is too large for {width}x{height} images: use a smaller one")
    return new_w, new_h


#: suffixes whose files keep an alpha channel losslessly (a JPEG copy of an RGBA image would drop it)
ALPHA_SUFFIXES = (".png", ".tif", ".tiff")


def derived_name(relative: Path, source: Path) -> Path:
    """The name of a derived copy of ``source``: its own, or ``.png`` when it has alpha that its format would lose."""
    if relative.suffix.lower() not in ALPHA_SUFFIXES and image_has_alpha(source):
        return relative.with_suffix(".png")
    return relative


def downscaled_paths(
    image_paths: list[Path], images_dir: Path, factor: int, cache_dir: Path | None = None
) -> list[Path]:
    """Paths of ``image_paths`` downscaled ``factor`` times (``cv2.INTER_AREA``), creating missing ones.

    Copies live in ``<images_dir name>_<factor>/`` (nerfstudio's layout) and keep the relative path and file name
    (an image with alpha in a format that cannot hold it, e.g. a PNG named .jpg, gets a .png copy: alpha survives).
    A copy already next to the images (shipped with the scene, or written there by an earlier run) is used as is;
    a missing one is written under :func:`derived_root`.
    """
    if factor == 1:
        return list(image_paths)

    folder = f"{images_dir.name}_{factor}"
    beside = images_dir.parent / folder
    derived = derived_root(images_dir, cache_dir) / folder
    out = []
    for path in image_paths:
        relative = derived_name(Path(path).relative_to(images_dir), Path(path))
        if cache_dir is None and derived_is_fresh(beside / relative, path, beside):
            out.append(beside / relative)
            continue
        target = derived / relative
        if not derived_is_fresh(target, path, derived):  # missing, or made from an older version of the source
            image = read_image(path)
            new_w, new_h = resized_size(image.shape[1], image.shape[0], factor)
            write_derived(target, cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_AREA), path, derived)
        out.append(target)
    return out

