"""``smgs download``'s work: from dataset and scene names to checked scene folders under the data root.

The order keeps every failure cheap and every name final only when complete: the scenes asked for are
planned, those already present and complete are skipped (an incomplete one stops the run before
anything is fetched, unless --force), the archives still needed are fetched into partial files
(resumed after an interruption) or taken from --from-file, each scene is unpacked into a temporary
folder, checked and renamed into place, and the manifest records the archive and the scenes.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from smgs.data.registry import get_dataset
from smgs.data.download.errors import ArchiveError, DownloadError
from smgs.data.download.fetch import open_remote, receive, sidecar
from smgs.data.download.manifest import Manifest, sha256_of
from smgs.data.download.sources import SOURCES, Archive, get_source
from smgs.data.download.unpack import check_space, human_size, open_zip, remove_stale, scene_problem, unpack_scene
from smgs.data.errors import DatasetNotFoundError

STAGING = ".smgs-download"   # under the data root (one file system): partial archives and the lock
ARCHIVE_NAMES = frozenset(a.name for src in SOURCES.values() for a in src.archives)


@dataclass(frozen=True)
class Wanted:
    """One scene to have: where it goes and how it is checked."""

    dataset: str
    scene: str
    target: Path
    expected: int | None
    folders: tuple[str, ...]
    archive: Archive

    @property
    def key(self) -> str:
        return f"{self.dataset}/{self.scene}"


@dataclass(frozen=True)
class DownloadRequest:
    """What ``smgs download`` was asked for, as plain values (smgs_cli/download.py makes it)."""

    datasets: tuple[str, ...]
    root: Path
    scenes: tuple[str, ...] = ()      # empty: each dataset's scenes of the paper (configs/dataset)
    from_file: Path | None = None     # an archive fetched by hand: no network
    mirror: str | None = None         # a base URL serving the archives under their names
    force: bool = False               # replace scenes that are present
    keep_archive: bool = False        # keep a downloaded archive after unpacking
    progress: bool | None = None      # progress bar: None = on a terminal only


@dataclass
class DownloadResult:
    unpacked: list[str] = field(default_factory=list)
    present: list[str] = field(default_factory=list)


def datasets_of_archive(path: Path) -> tuple[str, ...]:
    """The datasets an archive file serves, by its name (tandt_db.zip: tandt and deepblending)."""
    found = tuple(d for d, src in SOURCES.items() if any(a.name == path.name for a in src.archives))
    if not found:
        known = ", ".join(sorted(ARCHIVE_NAMES))
        raise ValueError(f"{path.name} is none of the archives smgs knows ({known}); name the "
                         "dataset it holds: smgs download DATASET --from-file FILE")
    return found


def plan(datasets: tuple[str, ...], scenes: tuple[str, ...], root: Path) -> list[Wanted]:
    """The scenes asked for, each with its dataset; a scene no named dataset has is refused."""
    if not datasets:
        raise ValueError(f"name a dataset to download: {', '.join(SOURCES)}")
    out, left = [], set(scenes)
    for d in dict.fromkeys(datasets):
        src, spec = get_source(d), get_dataset(d)
        known = spec.scenes + spec.extra_scenes
        chosen = [s for s in dict.fromkeys(scenes) if s in known] if scenes else list(spec.scenes)
        left -= set(chosen)
        out += [Wanted(d, s, root / spec.folders[0] / s, src.image_counts.get(s), src.image_folders,
                       src.archive_of(s)) for s in chosen]
    if left:
        have = "; ".join(f"{d}: {', '.join(get_dataset(d).scenes + get_dataset(d).extra_scenes)}"
                         for d in dict.fromkeys(datasets))
        raise ValueError(f"unknown scene(s) {', '.join(sorted(left))} for {', '.join(datasets)} ({have})")
    return out


def is_present(w: Wanted, root: Path, force: bool) -> bool:
    """True for a scene already complete under the root; an incomplete one is refused (nothing of a
    user's is overwritten unasked), and with ``force`` every scene is fetched again."""
    try:
        existing = get_dataset(w.dataset).scene_dir(root, w.scene)
    except DatasetNotFoundError:
        return False
    if force:
        return False
    _, problem = scene_problem(existing, w.expected, w.folders)
    if problem:
        raise DownloadError(f"{existing} exists but is incomplete: {problem}. Pass --force to replace it with "
                            "the archive's copy, or move it away")
    return True


def source_url(archive: Archive, mirror: str | None) -> str:
    """The authors' URL, or the archive's name under a mirror's base URL."""
    return f"{mirror.rstrip('/')}/{archive.name}" if mirror else archive.url


def download_command(datasets: tuple[str, ...], scenes: tuple[str, ...], root: Path | str,
                     from_file: str | None = None) -> str:
    """The ``smgs download`` command line that gets ``scenes`` of ``datasets`` under ``root``."""
    return (f"smgs download {' '.join(dict.fromkeys(datasets))} --scenes {','.join(scenes)} --root {root}"
            + (f" --from-file {from_file}" if from_file else ""))


def manual_hint(archive: Archive, group: list[Wanted], root: Path) -> str:
    """How to fetch by hand: which file, and how to hand it over."""
    cmd = download_command(tuple(w.dataset for w in group), tuple(w.scene for w in group), root,
                           f"/path/to/{archive.name}")
    return (f"fetch {archive.url} ({archive.size_text}) where there is network, copy it to this machine and "
            f"run: {cmd}")


def remedy(archive: Archive, path: Path, given: bool) -> str:
    """What to do with an archive that is damaged or not the expected one. One this run downloaded
    may be deleted and fetched again; a file the user gave (--from-file) is theirs: it is said not
    to be the expected archive, and left alone."""
    if not given:
        return "delete it and rerun to fetch it again"
    return (f"{path} is not the {archive.name} its authors publish ({archive.url}); pass that archive with "
            f"--from-file, or leave --from-file out to download it ({path} is left as it is)")


def download(req: DownloadRequest, log: Callable[[str], None] = print) -> DownloadResult:
    """Make every scene of ``req`` present and complete under ``req.root``."""
    root = req.root.expanduser()
    root.mkdir(parents=True, exist_ok=True)
    result, todo = DownloadResult(), []
    for w in plan(req.datasets, req.scenes, root):
        if is_present(w, root, req.force):
            result.present.append(w.key)
        else:
            todo.append(w)
    if result.present:
        log(f"present and complete, skipped: {', '.join(result.present)} (--force fetches them again)")
    groups: dict[str, list[Wanted]] = {}
    for w in todo:
        groups.setdefault(w.archive.name, []).append(w)
    if req.from_file is not None and len(groups) > 1:
        raise DownloadError(f"--from-file gives one archive, but these scenes come from {', '.join(groups)}: "
                            "name the scenes of one archive with --scenes")
    if not groups:
        return result
    with exclusive(root / STAGING):
        manifest = Manifest.read(root)
        for group in groups.values():
            result.unpacked += _fetch_and_unpack(group[0].archive, group, req, root, manifest, log)
    return result


@contextlib.contextmanager
def exclusive(staging: Path) -> Iterator[None]:
    """One download at a time into a data root (two would write the same partial file and manifest).
    The lock is the kernel's (flock): a killed run leaves nothing that blocks the next."""
    import fcntl

    staging.mkdir(parents=True, exist_ok=True)
    with open(staging / "lock", "w") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise DownloadError(f"another smgs download is writing into {staging.parent} (it holds {f.name}); let "
                                "it finish, or stop it and rerun") from None
        yield


def _fetch_and_unpack(archive: Archive, group: list[Wanted], req: DownloadRequest, root: Path,
                      manifest: Manifest, log: Callable[[str], None]) -> list[str]:
    path, downloaded = _local_archive(archive, group, req, root, manifest, log)
    fix = remedy(archive, path, req.from_file is not None)
    digest = _verify(archive, path, manifest, log, fix)
    with open_zip(path, fix) as zf:
        counts = {}
        for w in group:
            remove_stale(w.target.parent)
            counts[w.key] = unpack_scene(zf, archive, w.scene, w.target, w.expected, w.folders, fix)
            log(f"{w.key}: {counts[w.key]} registered images -> {w.target}")
    if archive.name not in manifest.archives:
        manifest.record_archive(archive.name, source_url(archive, req.mirror), path.stat().st_size, digest,
                                str(path) if req.from_file else None)
    for w in group:
        manifest.record_scene(w.key, archive.name, counts[w.key])
    if downloaded and not req.keep_archive:
        path.unlink()
    return [w.key for w in group]


def _verify(archive: Archive, path: Path, manifest: Manifest, log: Callable[[str], None], fix: str) -> str:
    """The archive's sha256, checked against a published one and the manifest's record; ``fix``:
    what to do with a mismatch (``remedy``)."""
    manifest.check_size(archive.name, path.stat().st_size, str(path))
    log(f"checking {path} (sha256)")
    digest = sha256_of(path)
    if archive.sha256 and digest != archive.sha256:
        raise ArchiveError(f"{path} has sha256 {digest}, not the published {archive.sha256}: {fix}")
    manifest.check_sha256(archive.name, digest, path, fix)
    return digest


def _local_archive(archive: Archive, group: list[Wanted], req: DownloadRequest, root: Path,
                   manifest: Manifest, log: Callable[[str], None]) -> tuple[Path, bool]:
    """The archive on disk, and whether this run downloaded it (to remove after unpacking)."""
    if req.from_file is not None:
        if not req.from_file.is_file():
            raise DownloadError(f"--from-file {req.from_file}: no such file")
        if req.from_file.name != archive.name and req.from_file.name in ARCHIVE_NAMES:
            raise DownloadError(f"--from-file {req.from_file} is {req.from_file.name}, but "
                                f"{', '.join(w.key for w in group)} come(s) from {archive.name}")
        return req.from_file, False
    final = root / STAGING / archive.name
    if final.is_file():
        log(f"using {final}, complete from an earlier run")
        return final, True
    url = source_url(archive, req.mirror)
    part = final.with_name(archive.name + ".part")
    part.parent.mkdir(parents=True, exist_ok=True)
    remote = open_remote(url, part, manual_hint(archive, group, root))
    try:
        manifest.check_size(archive.name, remote.total, f"the archive at {url}")
        total = remote.total or archive.approx_bytes or 0
        unpacked = total * len(group) // len(archive.members)
        left = remote.remaining if remote.remaining is not None else total
        check_space(part.parent, left + unpacked,
                    f"downloading {archive.name} and unpacking {len(group)} of its {len(archive.members)} scenes")
        log(f"downloading {url} ({human_size(remote.total) if remote.total else archive.size_text}) to {part}"
            + (f", resuming at {human_size(remote.offset)}" if remote.offset else ""))
        receive(remote, part, req.progress)
    finally:
        remote.close()
    os.replace(part, final)
    sidecar(part).unlink(missing_ok=True)
    return final, True
