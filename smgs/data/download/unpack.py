"""From a downloaded zip to one scene folder: check the archive, find the scene in it, extract it into
a temporary folder beside its final place, check it, and rename it into place.

A scene is complete when its COLMAP model reads, registers the dataset's image count (where a public
source gives it) and every registered image is in each image folder the dataset ships.

Each refusal ends with a ``remedy`` the caller words (``smgs.data.download.get.remedy``): a downloaded
archive may be deleted and fetched again; a file the user gave with --from-file is never to be
deleted, only said not to be the expected archive.
"""

from __future__ import annotations

import errno
import math
import os
import shutil
import tempfile
import zipfile
from pathlib import Path, PurePosixPath

from smgs.data.download.errors import ArchiveError, DiskSpaceError
from smgs.data.download.sources import Archive


# The file system's own share of an unpacked scene beyond its files' blocks (extent trees, directory
# growth, the journal's reservations): a scene that fits to the byte fails midway.
METADATA_SHARE = 0.01


def open_zip(path: Path, remedy: str) -> zipfile.ZipFile:
    try:
        return zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError) as e:
        raise ArchiveError(f"{path} is not a valid zip archive ({e}): {remedy}") from None


def scene_members(zf: zipfile.ZipFile, archive: Archive, scene: str,
                  remedy: str) -> tuple[str, list[zipfile.ZipInfo]]:
    """The scene's folder in the archive and its files. The folder is the one the archive is known to
    use, else the only ``.../<scene>/`` with a ``sparse/`` below it (an archive repacked with an
    extra top folder). A path that would leave the folder, or a file where the archive also has
    files below it (a file where a folder must be), refuses the archive before anything is written."""
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
    _refuse_file_as_folder(members, prefix, archive, remedy)
    return prefix, members


def _refuse_file_as_folder(members: list[zipfile.ZipInfo], prefix: str, archive: Archive, remedy: str) -> None:
    """An archive holding ``a/b`` as a file and ``a/b/c`` too cannot be unpacked: name both."""
    files = {str(PurePosixPath(i.filename[len(prefix):])): i.filename for i in members}
    for rel, name in files.items():
        for folder in PurePosixPath(rel).parents:
            if str(folder) in files:
                raise ArchiveError(f"{archive.name} holds {files[str(folder)]} as a file and also {name} below it: "
                                   f"a file where a folder must be, so the scene cannot be unpacked; it is not the "
                                   f"archive its authors publish: {remedy}")


def _block_size(folder: Path) -> int:
    try:
        return os.statvfs(folder).f_frsize or 4096
    except (OSError, AttributeError):   # no statvfs (Windows): the common block size
        return 4096


def folders_of(members: list[zipfile.ZipInfo]) -> set[str]:
    """The folders the members' paths make (their prefix's among them)."""
    return {str(p) for i in members for p in PurePosixPath(i.filename).parents}


def footprint(members: list[zipfile.ZipInfo], block: int) -> int:
    """Bytes the members take on a file system of ``block``-byte blocks: each file rounded up to
    whole blocks, a block per folder, and ``METADATA_SHARE`` on top (the declared sizes alone are
    what a full disk fails on midway)."""
    files = sum(math.ceil(i.file_size / block) * block for i in members)
    return math.ceil((files + len(folders_of(members)) * block) * (1 + METADATA_SHARE))


def check_inodes(folder: Path, needed: int, what: str) -> None:
    """Refuse before writing where ``folder``'s file system has fewer free inodes than files and
    folders to make (a file system may run out of them with bytes to spare)."""
    try:
        free = os.statvfs(folder).f_favail
    except (OSError, AttributeError):
        return
    if 0 < free < needed:   # 0: a file system that does not count them (btrfs, some network ones)
        raise DiskSpaceError(f"not enough free inodes in {folder}: {what} makes {needed} files and folders, the "
                             f"file system has room for {free} more. Free some, or pass --root DIR on another disk")


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


def extract(zf: zipfile.ZipFile, prefix: str, members: list[zipfile.ZipInfo], dest: Path, remedy: str) -> None:
    """The members into ``dest`` (their path below ``prefix``). A member whose CRC fails is an
    ArchiveError naming it."""
    for info in members:
        out = dest / info.filename[len(prefix):]
        out.parent.mkdir(parents=True, exist_ok=True)
        try:
            with zf.open(info) as src, open(out, "wb") as dst:
                shutil.copyfileobj(src, dst, 1 << 20)
        except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, ValueError) as e:
            raise ArchiveError(f"{zf.filename} is corrupt: {info.filename} cannot be read ({e}): {remedy}") from None


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
                 folders: tuple[str, ...], remedy: str) -> int:
    """Extract ``scene`` into a temporary folder beside ``target``, check it, and put it in place of
    ``target`` (an existing one is replaced in one step). Returns its registered image count. A disk
    that fills up all the same (another writer, a quota) is a ``DiskSpaceError`` saying how much
    the scene needs there; nothing is left behind."""
    from smgs.atomic import replace_dir

    prefix, members = scene_members(zf, archive, scene, remedy)
    target.parent.mkdir(parents=True, exist_ok=True)
    what = f"unpacking {scene} from {archive.name}"
    need = footprint(members, _block_size(target.parent))
    check_space(target.parent, need, what)
    check_inodes(target.parent, len(members) + len(folders_of(members)), what)
    tmp = None
    try:
        tmp = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{scene}.partial-"))
        extract(zf, prefix, members, tmp, remedy)
        n, problem = scene_problem(tmp, expected, folders)
        if problem:
            raise ArchiveError(f"scene {scene!r} in {archive.name} is incomplete: {problem}. Is it the right "
                               f"archive? {remedy[:1].upper()}{remedy[1:]}")
        replace_dir(tmp, target)
    except BaseException as e:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
            raise _filled_up(target.parent, what, need, e) from None
        raise
    return n


def _filled_up(folder: Path, what: str, need: int, e: OSError) -> DiskSpaceError:
    free = shutil.disk_usage(folder).free   # after the partial folder is gone
    return DiskSpaceError(f"the disk holding {folder} filled up while {what} ({e.strerror}): it needs about "
                          f"{human_size(need)} there, {human_size(free)} are free now; the partial folder was removed "
                          "and nothing was put in place. Free some space (or pass --root DIR on a larger disk) and "
                          "rerun")


def stale_partials(folder: Path) -> list[Path]:
    """Temporary scene folders an interrupted run left (never a final name)."""
    return sorted(p for p in folder.glob(".*.partial-*") if p.is_dir()) if folder.is_dir() else []


def remove_stale(folder: Path) -> None:
    for p in stale_partials(folder):
        shutil.rmtree(p, ignore_errors=True)
