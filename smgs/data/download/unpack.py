"""From a downloaded zip to one scene folder: check the archive, find the scene in it, extract it into
a temporary folder beside its final place, check it, and rename it into place.

A scene is complete when its COLMAP model reads, registers the dataset's image count (where a public
source gives it) and every registered image is in each image folder the dataset ships.
"""

from __future__ import annotations

import shutil
import tempfile
import zipfile
from pathlib import Path, PurePosixPath

from smgs.data.download.errors import ArchiveError, DiskSpaceError
from smgs.data.download.sources import Archive


def open_zip(path: Path) -> zipfile.ZipFile:
    try:
        return zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as e:
        raise ArchiveError(f"{path} is not a valid zip archive ({e}): delete it and rerun to fetch it again, "
                           "or give a complete copy with --from-file") from None


def scene_members(zf: zipfile.ZipFile, archive: Archive, scene: str) -> tuple[str, list[zipfile.ZipInfo]]:
    """The scene's folder in the archive and its files. The folder is the one the archive is known to
    use, else the only ``.../<scene>/`` with a ``sparse/`` below it (an archive repacked with an
    extra top folder)."""
    names = zf.namelist()
    prefix = archive.members[scene]
    if not any(n.startswith(prefix) for n in names):
        found = {n[:n.index(f"{scene}/sparse/") + len(scene) + 1] for n in names
                 if n.startswith(f"{scene}/sparse/") or f"/{scene}/sparse/" in n}
        if len(found) != 1:
            tops = sorted({n.split("/")[0] + "/" for n in names})
            raise ArchiveError(f"scene {scene!r} is missing from {archive.name}: no folder {prefix} (nor one "
                               f"other folder ending in {scene}/ with a COLMAP model); the archive's top folders "
                               f"are {', '.join(tops[:12]) or 'none'}. Is it the right file?")
        prefix = found.pop()
    members = [i for i in zf.infolist() if i.filename.startswith(prefix) and not i.is_dir()]
    for i in members:
        rel = PurePosixPath(i.filename[len(prefix):])
        if rel.is_absolute() or ".." in rel.parts or "\\" in i.filename:
            raise ArchiveError(f"{archive.name} holds {i.filename!r}, a path that would leave the scene folder; "
                               "refusing to unpack it")
    return prefix, members


def unpacked_size(members: list[zipfile.ZipInfo]) -> int:
    return sum(i.file_size for i in members)


def check_space(folder: Path, needed: int, what: str) -> None:
    """Refuse before writing anything when ``folder``'s file system has less than ``needed`` free."""
    free = shutil.disk_usage(folder).free
    if free < needed:
        raise DiskSpaceError(f"not enough free space in {folder}: {what} needs {human_size(needed)}, "
                             f"{human_size(free)} are free. Free some space, or pass --root DIR on a larger disk")


def human_size(n: int) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} bytes"


def extract(zf: zipfile.ZipFile, prefix: str, members: list[zipfile.ZipInfo], dest: Path) -> None:
    """The members into ``dest`` (their path below ``prefix``). A member whose CRC fails is an
    ArchiveError naming it."""
    for info in members:
        out = dest / info.filename[len(prefix):]
        out.parent.mkdir(parents=True, exist_ok=True)
        try:
            with zf.open(info) as src, open(out, "wb") as dst:
                shutil.copyfileobj(src, dst, 1 << 20)
        except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, ValueError) as e:
            raise ArchiveError(f"{zf.filename} is corrupt: {info.filename} cannot be read ({e}). Delete the "
                               "archive and rerun to fetch it again") from None


def scene_problem(scene_dir: Path, expected: int | None, folders: tuple[str, ...]) -> tuple[int, str | None]:
    """(registered images, None) for a complete scene, else (count so far, what is wrong)."""
    from smgs.data.colmap import find_model_dir, read_colmap_model
    from smgs.data.images import find_image
    from smgs.data.errors import DatasetNotFoundError, SceneFormatError

    try:
        model = read_colmap_model(find_model_dir(scene_dir), with_points=False)
    except (SceneFormatError, DatasetNotFoundError) as e:
        return 0, str(e)
    n = len(model.images)
    if expected is not None and n != expected:
        return n, f"its COLMAP model registers {n} images where the dataset has {expected}"
    for folder in folders:
        missing = [im.name for im in model.images if find_image(scene_dir / folder, im.name) is None]
        if missing:
            return n, (f"{scene_dir / folder} lacks {len(missing)} of the {n} registered images "
                       f"(first: {missing[0]})")
    return n, None


def unpack_scene(zf: zipfile.ZipFile, archive: Archive, scene: str, target: Path, expected: int | None,
                 folders: tuple[str, ...]) -> int:
    """Extract ``scene`` into a temporary folder beside ``target``, check it, and put it in place of
    ``target`` (an existing one is replaced in one step). Returns its registered image count."""
    from smgs.atomic import replace_dir

    prefix, members = scene_members(zf, archive, scene)
    target.parent.mkdir(parents=True, exist_ok=True)
    check_space(target.parent, unpacked_size(members), f"unpacking {scene} from {archive.name}")
    tmp = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{scene}.partial-"))
    try:
        extract(zf, prefix, members, tmp)
        n, problem = scene_problem(tmp, expected, folders)
        if problem:
            raise ArchiveError(f"scene {scene!r} in {archive.name} is incomplete: {problem}. Is it the right "
                               "archive? Delete it and rerun to fetch it again")
        replace_dir(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return n


def stale_partials(folder: Path) -> list[Path]:
    """Temporary scene folders an interrupted run left (never a final name)."""
    return sorted(p for p in folder.glob(".*.partial-*") if p.is_dir()) if folder.is_dir() else []


def remove_stale(folder: Path) -> None:
    for p in stale_partials(folder):
        shutil.rmtree(p, ignore_errors=True)
