"""Helpers for data tests: variants of a shared scene built in a temp folder (images copied: a few MB; the parsers
refuse symlinks that lead out of the scene)."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path


def scene_variant(
    src: Path,
    dst: Path,
    *,
    drop_model_images: tuple[str, ...] = (),
    drop_image_files: tuple[str, ...] = (),
    rename: Callable[[str], str] | None = None,
    cameras_txt: str | None = None,
    edit_image_line: Callable[[list[str]], list[str]] | None = None,
    train_list: list[str] | None = None,
    test_list: list[str] | None = None,
    with_lists: bool = True,
) -> Path:
    """A scene like ``src`` (images/ + sparse/0 text model [+ lists]) at ``dst`` with the given edits."""
    rename = rename or (lambda name: name)
    (dst / "images").mkdir(parents=True)
    for image in sorted((src / "images").iterdir()):
        if image.name not in drop_image_files:
            shutil.copyfile(image, dst / "images" / rename(image.name))
    model = dst / "sparse" / "0"
    model.mkdir(parents=True)
    src_model = src / "sparse" / "0"
    (model / "cameras.txt").write_text(cameras_txt or (src_model / "cameras.txt").read_text())
    lines = (src_model / "images.txt").read_text().splitlines()
    out, i, dropped_ids = [], 0, set()
    while i < len(lines):
        if lines[i].startswith("#"):
            out.append(lines[i])
            i += 1
            continue
        fields, points = lines[i].split(), lines[i + 1]
        i += 2
        if fields[9] in drop_model_images:
            dropped_ids.add(fields[0])
            continue
        fields[9] = rename(fields[9])
        if edit_image_line is not None:
            fields = edit_image_line(fields)
        out += [" ".join(fields), points]
    (model / "images.txt").write_text("\n".join(out) + "\n")
    # tracks must not reference images that were dropped from the model
    points = []
    for line in (src_model / "points3D.txt").read_text().splitlines():
        if not line.startswith("#") and dropped_ids:
            fields = line.split()
            track = [(a, b) for a, b in zip(fields[8::2], fields[9::2]) if a not in dropped_ids]
            line = " ".join(fields[:8] + [v for pair in track for v in pair])
        points.append(line)
    (model / "points3D.txt").write_text("\n".join(points) + "\n")
    if with_lists:
        for name, given in (("train_list.txt", train_list), ("test_list.txt", test_list)):
            names = given if given is not None else (src / name).read_text().split()
            (dst / name).write_text("".join(f"{rename(n)}\n" for n in names))
    return dst
