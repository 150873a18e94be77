"""The record beside the data of what was downloaded: ``<data root>/smgs-downloads.json``.

For each archive: URL, size in bytes, sha256 and date of the first complete download (or of the
file given with --from-file); for each scene unpacked: the archive it came from, its registered
images and the date. A later run checks the server's size and a new archive's sha256 against it,
so a file that changed at the source is noticed instead of mixed with scenes of the earlier one.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from smgs.atomic import atomic_write_text
from smgs.data.download.errors import ArchiveError, DownloadError, RemoteChangedError

MANIFEST = "smgs-downloads.json"


def now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass
class Manifest:
    path: Path
    archives: dict[str, dict] = field(default_factory=dict)
    scenes: dict[str, dict] = field(default_factory=dict)

    @classmethod
    def read(cls, root: Path) -> Manifest:
        path = Path(root) / MANIFEST
        if not path.exists():
            return cls(path)
        try:
            data = json.loads(path.read_text())
            return cls(path, dict(data["archives"]), dict(data["scenes"]))
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise DownloadError(f"cannot read the download manifest {path} ({e}); move it away to start a new "
                                "one (the scenes beside it are kept, and checked again)") from None

    def save(self) -> None:
        atomic_write_text(self.path, json.dumps({"archives": self.archives, "scenes": self.scenes},
                                                indent=2, sort_keys=True) + "\n")

    def record_archive(self, name: str, url: str, size: int, sha256: str, from_file: str | None = None) -> None:
        entry = {"url": url, "size": size, "sha256": sha256, "date": now()}
        if from_file:
            entry["from_file"] = from_file
        self.archives[name] = entry
        self.save()

    def record_scene(self, key: str, archive: str, images: int) -> None:
        self.scenes[key] = {"archive": archive, "sha256": self.archives.get(archive, {}).get("sha256"),
                            "images": images, "date": now()}
        self.save()

    def check_size(self, name: str, size: int | None, where: str) -> None:
        """A size other than the recorded one: the file changed at its source."""
        known = self.archives.get(name)
        if known and size is not None and size != known["size"]:
            raise RemoteChangedError(
                f"{where} is {size} bytes, but {name} was {known['size']} bytes when first downloaded on "
                f"{known['date']} ({self.path}): the archive has changed. To take the new one, delete its "
                f"entry in {self.path} (or the whole file) and rerun; scenes unpacked from the old one stay "
                "until you pass --force")

    def check_sha256(self, name: str, sha256: str, path: Path, fix: str) -> None:
        """``fix``: what to do with a file that is not the recorded one (to delete one this run
        downloaded; never one the user gave)."""
        known = self.archives.get(name)
        if known and sha256 != known["sha256"]:
            raise ArchiveError(
                f"{path} has sha256 {sha256}, but {name} had {known['sha256']} when first downloaded on "
                f"{known['date']} ({self.path}): {fix}; or, to accept this file, delete the entry of {name} in "
                f"{self.path}")
