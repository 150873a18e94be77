"""``smgs download DATASET... [--scenes ...] [--root DIR]``: the paper's datasets from the archives
their authors publish, into the layout the harness reads (smgs.data.download; docs/usage.md,
"Downloading the datasets")."""

from __future__ import annotations

import argparse
import os
import textwrap
import sys
from pathlib import Path

from smgs.data.datasets import DATA_ROOT_ENV
from smgs.data.registry import get_dataset
from smgs.data.download import MANIFEST, SOURCES, DownloadError, DownloadRequest, datasets_of_archive, download
from smgs.data.download.get import STAGING


def datasets_text() -> str:
    """Each dataset's archive, URL, size, scenes, layout and terms: --help's epilog, from the facts."""
    out = []
    for name, src in SOURCES.items():
        spec = get_dataset(name)
        out.append(f"{name}: scenes {', '.join(spec.scenes)} (the paper's; also {', '.join(spec.extra_scenes)})"
                   if spec.extra_scenes else f"{name}: scenes {', '.join(spec.scenes)}")
        for a in src.archives:
            out.append(f"  {a.name}, {a.size_text}: {a.url}")
        folders = ",".join(src.image_folders)
        out.append(f"  layout: $ROOT/{spec.folders[0]}/<scene>/{'{' + folders + '}' if ',' in folders else folders}/ "
                   "and <scene>/sparse/0/{cameras,images,points3D}.bin")
        out.append(f"  terms you accept by downloading: {src.terms}; " + "; ".join(src.pages))
    return "\n".join(out)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="smgs download", formatter_class=argparse.RawDescriptionHelpFormatter,
        description=textwrap.fill(
            "Fetch the paper's datasets from the archives their authors publish, check them and unpack them into "
            "the layout the harness reads. A download is resumed after an interruption; scenes already present "
            "and complete are skipped; the archive's URL, size, sha256 and date are recorded in "
            f"$ROOT/{MANIFEST} and checked on later runs. Needs free space for the archive and the scenes "
            "unpacked from it (the archive is removed afterwards).", 100, break_on_hyphens=False),
        epilog=datasets_text() + "\n\nWithout network: fetch the archive elsewhere and pass it with --from-file.")
    p.add_argument("datasets", nargs="*", metavar="DATASET", help=f"one or more of {', '.join(SOURCES)} "
                   "(optional with --from-file: the archive's name says which)")
    p.add_argument("--scenes", nargs="+", default=[], metavar="SCENE",
                   help="only these scenes (names or comma-separated lists); default: the paper's scenes")
    p.add_argument("--root", type=Path, help=f"the data root (default ${DATA_ROOT_ENV})")
    p.add_argument("--from-file", type=Path, metavar="ARCHIVE", help="an archive fetched by hand: no network")
    p.add_argument("--mirror", metavar="URL", help="fetch ARCHIVE_NAME from URL/ARCHIVE_NAME instead of the "
                   "authors' servers (a local copy of the archives)")
    p.add_argument("--force", action="store_true", help="fetch and replace scenes that are already present")
    p.add_argument("--keep-archive", action="store_true", help=f"keep a downloaded archive in $ROOT/{STAGING}/")
    return p


def request(args: argparse.Namespace) -> DownloadRequest:
    root = args.root or os.environ.get(DATA_ROOT_ENV)
    if not root:
        raise ValueError(f"no data root: pass --root DIR or set ${DATA_ROOT_ENV}")
    datasets = tuple(args.datasets)
    if not datasets and args.from_file is not None:
        datasets = datasets_of_archive(args.from_file)
    scenes = tuple(s for item in args.scenes for s in item.split(",") if s)
    return DownloadRequest(datasets=datasets, root=Path(root), scenes=scenes, from_file=args.from_file,
                           mirror=args.mirror, force=args.force, keep_archive=args.keep_archive)


def main(argv: list[str]) -> int:
    args = parser().parse_args(argv)
    try:
        req = request(args)
        for d in dict.fromkeys(req.datasets):
            if d in SOURCES:
                print(f"{d}: by downloading you accept {SOURCES[d].terms} ({'; '.join(SOURCES[d].pages)})")
        result = download(req)
    except (ValueError, DownloadError) as e:
        print(f"smgs download: {e}", file=sys.stderr)
        return 2 if isinstance(e, ValueError) else 1
    except KeyboardInterrupt:
        print("smgs download: interrupted; what arrived is kept: rerun the same command to resume", file=sys.stderr)
        return 130
    print(f"done: {len(result.unpacked)} scene(s) unpacked, {len(result.present)} already present, under {req.root}"
          + ("" if os.environ.get(DATA_ROOT_ENV) == str(req.root) else f" (export {DATA_ROOT_ENV}={req.root})"))
    return 0
