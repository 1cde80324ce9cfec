"""Names read from scene files (split lists, ``images.txt``, ``transforms.json``) must stay inside the scene.

A name that is absolute, climbs with ``..``, or resolves (through a symlink) outside its folder is refused: such a
scene would read files from anywhere, and the undistortion / downscale caches, which keep the name's relative path,
would be written outside the scene's cache folder.
"""

from __future__ import annotations

from pathlib import Path, PurePosixPath, PureWindowsPath

from kc_splatfacto.data.base import DataParserError


def inside_folder(folder: Path, name: str | Path, source: str, allow_symlinks_out: bool = False) -> Path:
    """``folder / name``, after checking that ``name`` (from ``source``, e.g. "train_list.txt line 3") stays inside.

    Args:
        folder: the folder names are relative to (the image folder, the transforms.json folder).
        name: the name as written in the file.
        source: where the name comes from, for the message.
        allow_symlinks_out: accept a path whose symlinks lead outside ``folder`` (the lexical checks still apply).
    Raises:
        DataParserError: naming the file, the name and why.
    """
    text = str(name)
    pure = PurePosixPath(text.replace("\\", "/"))
    if pure.is_absolute() or PureWindowsPath(text).is_absolute() or PureWindowsPath(text).drive:
        raise DataParserError(
            f"{source}: '{text}' is an absolute path; names must be relative to {folder} (move the file into the scene)"
        )
    if ".." in pure.parts:
        raise DataParserError(
            f"{source}: '{text}' climbs out of {folder} with '..'; names must stay inside the scene folder"
        )
    path = Path(folder) / text
    if not allow_symlinks_out and path.exists():
        root = Path(folder).resolve()
        if not path.resolve().is_relative_to(root):
            raise DataParserError(
                f"{source}: '{text}' leads (through a symlink) to {path.resolve()}, outside {root}: copy the file into "
                "the scene, or set the dataparser config's allow_symlinks_out to read it there"
            )
    return path


def check_names_inside(folder: Path, names: list[str], source: str, allow_symlinks_out: bool = False) -> list[Path]:
    """:func:`inside_folder` for each name; returns the paths."""
    return [inside_folder(folder, name, source, allow_symlinks_out) for name in names]
