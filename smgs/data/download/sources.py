"""Where the paper's datasets come from: the archives their authors publish, the scenes each holds,
the registered image count of each scene, and the terms a user accepts by downloading them.

These are facts of the datasets, kept here and not in configs/dataset/*.yaml: a cell's dataset config
is part of its result's hash, so a field added there would make every finished real-data cell look
new and retrain. Where each fact comes from is written beside it; what no public source confirmed is
None and is said so (an archive's exact size and sha256 are recorded in the data root's manifest on
the first download and checked on every later one).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping


@dataclass(frozen=True)
class Archive:
    """One file the authors publish.

    members: scene -> its folder inside the archive (with the trailing slash).
    size_text: its size in words for --help and the docs, with the source; approx_bytes the same
        as a number, for the disk check before the server has answered (None: unknown).
    """

    name: str
    url: str
    members: Mapping[str, str]
    size_text: str
    approx_bytes: int | None
    sha256: str | None = None   # no public source gives it: the manifest records it on first download


@dataclass(frozen=True)
class DatasetSource:
    """A dataset's archives, its scenes' registered image counts (None: not confirmed by a public
    source, so only 'has images and a COLMAP model' is checked) and its terms of use."""

    dataset: str
    archives: tuple[Archive, ...]
    image_counts: Mapping[str, int | None]
    image_folders: tuple[str, ...]   # each must hold every registered image after extraction
    terms: str
    pages: tuple[str, ...] = field(default=())

    def archive_of(self, scene: str) -> Archive:
        for a in self.archives:
            if scene in a.members:
                return a
        raise ValueError(f"no {self.dataset} archive holds scene {scene!r}; the archives hold "
                         f"{', '.join(s for a in self.archives for s in a.members)}")


# URLs: gsplat examples/datasets/download_dataset.py and nerfbaselines datasets/mipnerf360.py (which
# also shows the scenes at the archive's top level, "<scene>/..."). Sizes: no public source agrees
# (third-party scripts say 3 to 25 GB), so the server's answer is what counts.
MIPNERF360_MAIN = Archive(
    name="360_v2.zip", url="https://storage.googleapis.com/gresearch/refraw360/360_v2.zip",
    members={s: f"{s}/" for s in ("bicycle", "bonsai", "counter", "garden", "kitchen", "room", "stump")},
    size_text="size not confirmed by a public source (the server's size is shown before anything is "
              "downloaded)", approx_bytes=None)
MIPNERF360_EXTRA = Archive(
    name="360_extra_scenes.zip", url="https://storage.googleapis.com/gresearch/refraw360/360_extra_scenes.zip",
    members={s: f"{s}/" for s in ("flowers", "treehill")},
    size_text="size not confirmed by a public source", approx_bytes=None)
# Its size is the one the 3DGS README gives (its link "T&T+DB COLMAP (650MB)"); the archive unpacks
# to tandt/<scene> and db/<scene> (the 3DGS README's `train.py -s data/tandt/truck`; nvs-bench's
# scripts/dataset_downloads/deepblending_and_tanksandtemples.sh).
TANDT_DB = Archive(
    name="tandt_db.zip", url="https://repo-sam.inria.fr/fungraph/3d-gaussian-splatting/datasets/input/tandt_db.zip",
    members={"train": "tandt/train/", "truck": "tandt/truck/",
             "drjohnson": "db/drjohnson/", "playroom": "db/playroom/"},
    size_text="650 MB according to the 3DGS README", approx_bytes=650 * 10**6)

# Registered images per scene, from published third-party tables that agree where they overlap:
# jaesung-cs/splatstream's bench/README.md (bicycle 194, bonsai 292, counter 240, garden 185,
# kitchen 279, room 311, truck 251, train 301), DirectXSplat's benchmark table (bicycle, garden,
# treehill 141), a Mip-NeRF360 training table (stump 125) and two 3DGS evaluation write-ups
# (drjohnson 263, playroom 225 cameras). No source found gives flowers' count.
UNNAMED = "no licence name is confirmed here: read the page before use"
REPACKED = "the archive is the 3DGS authors' COLMAP repackaging of the scenes"
THREEDGS_PAGE = "https://github.com/graphdeco-inria/gaussian-splatting (README: T&T+DB COLMAP)"

SOURCES: dict[str, DatasetSource] = {
    "mipnerf360": DatasetSource(
        dataset="mipnerf360", archives=(MIPNERF360_MAIN, MIPNERF360_EXTRA),
        image_counts={"bicycle": 194, "bonsai": 292, "counter": 240, "garden": 185, "kitchen": 279,
                      "room": 311, "stump": 125, "flowers": None, "treehill": 141},
        image_folders=("images", "images_2", "images_4", "images_8"),
        terms=f"the Mip-NeRF 360 authors' terms on their page ({UNNAMED})",
        pages=("https://jonbarron.info/mipnerf360/",)),
    "tandt": DatasetSource(
        dataset="tandt", archives=(TANDT_DB,), image_counts={"train": 301, "truck": 251}, image_folders=("images",),
        terms=f"the Tanks and Temples licence (its page); {REPACKED}",
        pages=("https://tanksandtemples.org/license/", THREEDGS_PAGE)),
    "deepblending": DatasetSource(
        dataset="deepblending", archives=(TANDT_DB,), image_counts={"drjohnson": 263, "playroom": 225},
        image_folders=("images",), terms=f"the Deep Blending authors' terms on their page ({UNNAMED}); {REPACKED}",
        pages=("http://visual.cs.ucl.ac.uk/pubs/deepblending/", THREEDGS_PAGE)),
}


def get_source(dataset: str) -> DatasetSource:
    if dataset not in SOURCES:
        raise ValueError(f"no download for dataset {dataset!r}; smgs download fetches "
                         f"{', '.join(SOURCES)}")
    return SOURCES[dataset]
