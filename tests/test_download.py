"""``smgs download`` against a server on 127.0.0.1 serving tiny archives in the real layout (the
scenes' real registered image counts, JPEG images, binary COLMAP models): a whole download, an
interruption then a resume with HTTP Range, a corrupt archive, a 404, a full disk, no network,
--from-file, and the manifest's checks on a later run. Nothing reaches outside the machine."""

from __future__ import annotations

import hashlib
import io
import json
import re
import socket
import zipfile
from collections import namedtuple
from pathlib import Path

import pytest

from download_server import Server, scene_files, tandt_db_zip, zip_bytes
from smgs.data.download import (MANIFEST, ArchiveError, DiskSpaceError, DownloadError, DownloadRequest,
                                NetworkError, RemoteChangedError, download)
from smgs.data.download import unpack
from smgs.data.download.get import STAGING

pytest.importorskip("pycolmap")

MIP_FOLDERS = ("images", "images_2", "images_4", "images_8")


@pytest.fixture(scope="module")
def tandt_db() -> bytes:
    return tandt_db_zip()


def _get(root: Path, server_url: str, *datasets: str, scenes: tuple[str, ...] = (), progress: bool = False, **kw):
    lines: list[str] = []
    req = DownloadRequest(datasets=datasets, root=root, scenes=scenes, mirror=server_url, progress=progress, **kw)
    return download(req, log=lines.append), lines


def _closed_port_url() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"http://127.0.0.1:{s.getsockname()[1]}"   # nobody listens once the socket closes


def _leftovers(root: Path) -> list[str]:
    """Names a failed run must not leave: scene folders, temporary folders."""
    return sorted(str(p.relative_to(root)) for p in root.rglob("*")
                  if p.is_dir() and (p.name.startswith(".") and "partial" in p.name or p.name in ("train", "truck")))


def test_a_whole_download_unpacks_the_layout_and_records_the_manifest(tmp_path, tandt_db):
    root = tmp_path / "data"
    with Server({"tandt_db.zip": tandt_db}) as srv:
        result, lines = _get(root, srv.url, "tandt", "deepblending")
    assert result.unpacked == ["tandt/train", "tandt/truck", "deepblending/drjohnson", "deepblending/playroom"]
    assert len(srv.requests) == 1, "one archive serves both datasets: fetched once"
    for folder, scene, n in (("tandt", "train", 301), ("tandt", "truck", 251), ("db", "drjohnson", 263),
                             ("db", "playroom", 225)):
        assert len(list((root / folder / scene / "images").iterdir())) == n
        assert (root / folder / scene / "sparse" / "0" / "images.bin").is_file()
    assert sorted(p.name for p in (root / STAGING).iterdir()) == ["lock"], "the archive is removed after unpacking"
    manifest = json.loads((root / MANIFEST).read_text())
    entry = manifest["archives"]["tandt_db.zip"]
    assert entry["size"] == len(tandt_db) and entry["sha256"] == hashlib.sha256(tandt_db).hexdigest()
    assert entry["url"].endswith("/tandt_db.zip") and entry["date"]
    assert manifest["scenes"]["tandt/train"]["images"] == 301
    assert any("tandt/train: 301 registered images" in line for line in lines)
    # The harness loads what was unpacked.
    from smgs.data import load_scene
    s = load_scene("tandt", scene="train", data_root=root, rule="3dgs")
    assert len(s.train) + len(s.test) == 301


def test_the_progress_bar_shows_bytes_rate_and_time_left(tmp_path, tandt_db, capsys):
    with Server({"tandt_db.zip": tandt_db}) as srv:
        _get(tmp_path / "data", srv.url, "tandt", scenes=("train",), progress=True)
    bar = capsys.readouterr().err.replace("\r", "\n").splitlines()[-1]
    from tqdm import tqdm
    size = tqdm.format_sizeof(len(tandt_db), divisor=1024)   # bytes in binary prefixes
    assert bar.startswith("tandt_db.zip: 100%") and f"{size}/{size}" in bar, bar
    assert re.search(r"\[\d\d:\d\d<\d\d:\d\d, +[\d.]+[kMG]?B/s\]", bar), bar   # elapsed<left, rate


def test_present_scenes_are_skipped_without_the_network_and_force_fetches_again(tmp_path, tandt_db):
    root = tmp_path / "data"
    with Server({"tandt_db.zip": tandt_db}) as srv:
        _get(root, srv.url, "tandt", scenes=("train",))
    result, lines = _get(root, _closed_port_url(), "tandt", scenes=("train",))
    assert result.present == ["tandt/train"] and result.unpacked == []
    assert "present and complete, skipped: tandt/train" in lines[0]
    marker = root / "tandt" / "train" / "mine.txt"
    marker.write_text("x")
    with Server({"tandt_db.zip": tandt_db}) as srv:
        result, _ = _get(root, srv.url, "tandt", scenes=("train",), force=True)
    assert result.unpacked == ["tandt/train"] and not marker.exists()


def test_an_incomplete_scene_is_refused_before_anything_is_fetched(tmp_path, tandt_db):
    root = tmp_path / "data"
    with Server({"tandt_db.zip": tandt_db}) as srv:
        _get(root, srv.url, "tandt", scenes=("truck",))
        victim = sorted((root / "tandt" / "truck" / "images").iterdir())[7]
        victim.unlink()
        with pytest.raises(DownloadError, match=rf"truck exists but is incomplete: .*lacks 1 of the 251 .*{victim.name}"
                                                r".*--force"):
            _get(root, srv.url, "tandt", scenes=("truck",))
        assert len(srv.requests) == 1


def test_an_interrupted_download_resumes_with_a_range_request(tmp_path, tandt_db):
    root = tmp_path / "data"
    cut = len(tandt_db) // 3
    with Server({"tandt_db.zip": tandt_db}) as srv:
        srv.cut_after["tandt_db.zip"] = cut
        with pytest.raises(NetworkError, match=rf"ended at byte {cut} of {len(tandt_db)}; rerun .* resume"):
            _get(root, srv.url, "tandt")
        part = root / STAGING / "tandt_db.zip.part"
        assert part.stat().st_size == cut
        assert not (root / "tandt").exists(), "nothing under a final name"
        result, lines = _get(root, srv.url, "tandt")
    assert srv.requests[1][1] == f"bytes={cut}-" and srv.requests[1][2] == srv.etag("tandt_db.zip")
    assert result.unpacked == ["tandt/train", "tandt/truck"]
    assert any("resuming at" in line for line in lines)
    sha = json.loads((root / MANIFEST).read_text())["archives"]["tandt_db.zip"]["sha256"]
    assert sha == hashlib.sha256(tandt_db).hexdigest()


def test_a_resume_of_a_file_changed_at_the_server_starts_over(tmp_path, tandt_db):
    root = tmp_path / "data"
    with Server({"tandt_db.zip": tandt_db}) as srv:
        srv.cut_after["tandt_db.zip"] = 1000
        with pytest.raises(NetworkError):
            _get(root, srv.url, "tandt")
        new = zip_bytes({"tandt/train/": scene_files(301), "tandt/truck/": scene_files(251)})
        srv.files["tandt_db.zip"] = new   # another file (another ETag): the earlier 1000 bytes are useless
        result, _ = _get(root, srv.url, "tandt")
    assert srv.requests[1][1] == "bytes=1000-", "asked to resume"
    assert result.unpacked == ["tandt/train", "tandt/truck"]
    assert json.loads((root / MANIFEST).read_text())["archives"]["tandt_db.zip"]["size"] == len(new)


def test_a_second_download_into_the_same_root_is_refused_while_one_runs(tmp_path, tandt_db):
    from smgs.data.download.get import exclusive

    root = tmp_path / "data"
    with exclusive(root / STAGING), Server({"tandt_db.zip": tandt_db}) as srv, \
            pytest.raises(DownloadError, match=rf"another smgs download is writing into {root} \(it holds "):
        _get(root, srv.url, "tandt")
    assert srv.requests == []
    with Server({"tandt_db.zip": tandt_db}) as srv:
        assert _get(root, srv.url, "tandt")[0].unpacked == ["tandt/train", "tandt/truck"]


def test_a_404_says_the_file_is_gone_and_how_to_fetch_it_by_hand(tmp_path):
    root = tmp_path / "data"
    with Server({}) as srv, pytest.raises(RemoteChangedError) as e:
        _get(root, srv.url, "deepblending")
    msg = str(e.value)
    assert "/tandt_db.zip answered HTTP 404" in msg
    assert ("https://repo-sam.inria.fr/fungraph/3d-gaussian-splatting/datasets/input/tandt_db.zip (650 MB" in msg
            and f"--root {root} --from-file /path/to/tandt_db.zip" in msg)
    assert not (root / "db").exists()


def test_a_server_failure_says_to_try_again_later(tmp_path):
    with Server({}) as srv, pytest.raises(NetworkError, match=r"answered HTTP 503 Service Unavailable, a failure of "
                                                              r"the server: try again later\. Without network here"):
        srv.failing.add("tandt_db.zip")
        _get(tmp_path / "data", srv.url, "tandt")


def test_no_network_names_the_file_to_fetch_by_hand_and_the_command_to_give_it(tmp_path):
    root = tmp_path / "data"
    with pytest.raises(NetworkError) as e:
        _get(root, _closed_port_url(), "mipnerf360", scenes=("stump", "garden"))
    msg = str(e.value)
    assert "cannot reach" in msg and "https://storage.googleapis.com/gresearch/refraw360/360_v2.zip" in msg
    assert f"smgs download mipnerf360 --scenes stump,garden --root {root} --from-file /path/to/360_v2.zip" in msg


def test_a_file_that_is_no_zip_is_refused_and_nothing_is_unpacked(tmp_path, tandt_db):
    root = tmp_path / "data"
    with Server({"tandt_db.zip": tandt_db[: len(tandt_db) // 2]}) as srv, \
            pytest.raises(ArchiveError, match=r"tandt_db\.zip is not a valid zip archive .*delete it and rerun"):
        _get(root, srv.url, "tandt")
    assert _leftovers(root) == [] and not (root / MANIFEST).exists()


def test_a_damaged_member_is_named_and_leaves_no_scene_behind(tmp_path):
    files = scene_files(301)
    good = zip_bytes({"tandt/train/": files, "tandt/truck/": scene_files(251)})
    victim = "tandt/train/images/frame_00042.jpg"
    with zipfile.ZipFile(io.BytesIO(good)) as zf:
        info = zf.getinfo(victim)
        at = info.header_offset + 30 + len(info.filename) + len(info.extra) + 2
    bad = good[:at] + bytes([good[at] ^ 0xFF]) + good[at + 1:]   # the CRC no longer matches
    root = tmp_path / "data"
    with Server({"tandt_db.zip": bad}) as srv, pytest.raises(ArchiveError, match=rf"is corrupt: {victim}"):
        _get(root, srv.url, "tandt")
    assert _leftovers(root) == [] and (root / STAGING / "tandt_db.zip").is_file(), "kept for inspection"


def test_a_scene_missing_from_the_archive_is_named(tmp_path):
    only_train = zip_bytes({"tandt/train/": scene_files(301)})
    with Server({"tandt_db.zip": only_train}) as srv, \
            pytest.raises(ArchiveError, match=r"scene 'truck' is missing from tandt_db\.zip: no folder tandt/truck/"
                                              r".*top folders are tandt/"):
        _get(tmp_path / "data", srv.url, "tandt")


def test_a_scene_with_the_wrong_image_count_is_refused(tmp_path):
    short = zip_bytes({"tandt/train/": scene_files(301, registered=300), "tandt/truck/": scene_files(251)})
    with Server({"tandt_db.zip": short}) as srv, \
            pytest.raises(ArchiveError, match=r"'train' in tandt_db\.zip is incomplete: its COLMAP model registers 300 "
                                              r"images where the dataset has 301"):
        _get(tmp_path / "data", srv.url, "tandt", scenes=("train",))
    assert _leftovers(tmp_path / "data") == []


def test_a_full_disk_is_refused_before_the_download_with_the_size_needed(tmp_path, tandt_db, monkeypatch):
    Usage = namedtuple("Usage", "total used free")
    monkeypatch.setattr(unpack.shutil, "disk_usage", lambda p: Usage(10**9, 10**9 - 5000, 5000))
    root = tmp_path / "data"
    with Server({"tandt_db.zip": tandt_db}) as srv, pytest.raises(DiskSpaceError) as e:
        _get(root, srv.url, "tandt")
    needed = len(tandt_db) + len(tandt_db) * 2 // 4   # the archive, and half of it unpacked (2 of 4 scenes)
    assert (f"not enough free space in {root / STAGING}: downloading tandt_db.zip and unpacking 2 of its 4 scenes "
            f"needs {unpack.human_size(needed)}, 5.0 kB are free. Free some space, or pass --root DIR") in str(e.value)
    assert not (root / STAGING / "tandt_db.zip.part").exists()


def test_a_full_disk_while_writing_keeps_what_arrived_for_a_rerun(tmp_path, tandt_db, monkeypatch):
    import errno

    from smgs.data.download import fetch

    real = fetch._write
    calls = []

    def filling(f, chunk, part):
        calls.append(len(chunk))
        if len(calls) > 1:
            f.write = lambda b: (_ for _ in ()).throw(OSError(errno.ENOSPC, "No space left on device"))
        real(f, chunk, part)

    monkeypatch.setattr(fetch, "CHUNK", 64 * 1024)
    monkeypatch.setattr(fetch, "_write", filling)
    root = tmp_path / "data"
    with Server({"tandt_db.zip": tandt_db}) as srv, \
            pytest.raises(DiskSpaceError, match=r"is full \(No space left on device\); what arrived is kept"):
        _get(root, srv.url, "tandt")
    assert (root / STAGING / "tandt_db.zip.part").stat().st_size == 64 * 1024


def _mipnerf_archive() -> bytes:
    return zip_bytes({"stump/": scene_files(125, MIP_FOLDERS), "garden/": scene_files(185, MIP_FOLDERS)})


def test_from_file_unpacks_without_the_network_and_records_the_file(tmp_path):
    archive = tmp_path / "hand" / "360_v2.zip"
    archive.parent.mkdir()
    archive.write_bytes(_mipnerf_archive())
    root = tmp_path / "data"
    result, _ = _get(root, _closed_port_url(), "mipnerf360", scenes=("stump",), from_file=archive)
    assert result.unpacked == ["mipnerf360/stump"]
    for folder in MIP_FOLDERS:
        assert len(list((root / "mipnerf360" / "stump" / folder).iterdir())) == 125
    entry = json.loads((root / MANIFEST).read_text())["archives"]["360_v2.zip"]
    assert entry["from_file"] == str(archive) and entry["size"] == archive.stat().st_size
    assert archive.is_file(), "a file given by hand is never removed"


def test_from_file_of_the_other_archive_is_refused_naming_both(tmp_path):
    archive = tmp_path / "360_v2.zip"
    archive.write_bytes(_mipnerf_archive())
    with pytest.raises(DownloadError, match=r"360_v2\.zip is 360_v2\.zip, but mipnerf360/flowers come\(s\) from "
                                            r"360_extra_scenes\.zip"):
        _get(tmp_path / "data", _closed_port_url(), "mipnerf360", scenes=("flowers",), from_file=archive)


def test_a_later_run_refuses_an_archive_that_changed_since_the_manifest(tmp_path, tandt_db):
    root = tmp_path / "data"
    with Server({"tandt_db.zip": tandt_db}) as srv:
        _get(root, srv.url, "tandt", scenes=("train",))
        srv.files["tandt_db.zip"] = tandt_db + b"\0" * 10
        with pytest.raises(RemoteChangedError, match=rf"is {len(tandt_db) + 10} bytes, but tandt_db\.zip was "
                                                     rf"{len(tandt_db)} bytes when first downloaded"):
            _get(root, srv.url, "tandt", scenes=("truck",))
    other = tmp_path / "tandt_db.zip"
    other.write_bytes(zip_bytes({"tandt/truck/": scene_files(251)}).ljust(len(tandt_db), b"\0"))
    with pytest.raises(ArchiveError, match=r"has sha256 [0-9a-f]{64}, but tandt_db\.zip had [0-9a-f]{64}") as e:
        _get(root, _closed_port_url(), "tandt", scenes=("truck",), from_file=other)
    assert "delete it" not in str(e.value) and f"{other} is left as it is" in str(e.value), "a user's own file"


def test_unknown_names_are_refused_with_what_exists(tmp_path):
    with pytest.raises(ValueError, match=r"unknown scene\(s\) bicycle for tandt \(tandt: train, truck\)"):
        _get(tmp_path, _closed_port_url(), "tandt", scenes=("bicycle",))
    with pytest.raises(ValueError, match=r"no download for dataset 'colmap'; smgs download fetches mipnerf360"):
        _get(tmp_path, _closed_port_url(), "colmap")


def test_the_command_downloads_and_says_the_terms_and_where_it_put_the_data(tmp_path, tandt_db, capsys, monkeypatch):
    from smgs_cli.main import main

    monkeypatch.delenv("SMGS_DATA_ROOT", raising=False)
    root = tmp_path / "data"
    with Server({"tandt_db.zip": tandt_db}) as srv:
        assert main(["download", "deepblending", "--scenes", "playroom", "--root", str(root), "--mirror", srv.url]) == 0
    out = capsys.readouterr().out
    assert "deepblending: by downloading you accept the Deep Blending authors' terms" in out
    assert "http://visual.cs.ucl.ac.uk/pubs/deepblending/" in out
    assert f"done: 1 scene(s) unpacked, 0 already present, under {root} (export SMGS_DATA_ROOT={root})" in out
    assert json.loads((root / MANIFEST).read_text())["archives"]["tandt_db.zip"]["url"] == f"{srv.url}/tandt_db.zip"


def test_the_command_takes_an_archive_by_hand_and_names_its_datasets_from_its_name(tmp_path, capsys, monkeypatch):
    from smgs_cli.main import main

    archive = tmp_path / "360_v2.zip"
    archive.write_bytes(_mipnerf_archive())
    monkeypatch.setenv("SMGS_DATA_ROOT", str(tmp_path / "data"))
    assert main(["download", "--from-file", str(archive), "--scenes", "stump,garden"]) == 0
    assert "done: 2 scene(s) unpacked" in capsys.readouterr().out
    assert main(["download", "--from-file", str(tmp_path / "other.zip")]) == 2
    assert "other.zip is none of the archives smgs knows (360_extra_scenes.zip, 360_v2.zip, tandt_db.zip)" in \
        capsys.readouterr().err


def test_the_command_without_a_root_or_with_a_failure_says_why(tmp_path, capsys, monkeypatch):
    from smgs_cli.main import main

    monkeypatch.delenv("SMGS_DATA_ROOT", raising=False)
    assert main(["download", "tandt"]) == 2
    assert "no data root: pass --root DIR or set $SMGS_DATA_ROOT" in capsys.readouterr().err
    assert main(["download", "tandt", "--root", str(tmp_path), "--mirror", _closed_port_url()]) == 1
    assert "smgs download: cannot reach" in capsys.readouterr().err


def test_help_gives_each_dataset_its_url_size_terms_and_layout(capsys):
    from smgs_cli.main import main

    with pytest.raises(SystemExit) as e:
        main(["download", "--help"])
    text = capsys.readouterr().out
    assert e.value.code == 0
    for url in ("https://storage.googleapis.com/gresearch/refraw360/360_v2.zip",
                "https://repo-sam.inria.fr/fungraph/3d-gaussian-splatting/datasets/input/tandt_db.zip",
                "https://jonbarron.info/mipnerf360/", "https://tanksandtemples.org/license/",
                "http://visual.cs.ucl.ac.uk/pubs/deepblending/"):
        assert url in text
    assert "tandt_db.zip, 650 MB according to the 3DGS README" in text and "360_v2.zip, size not confirmed" in text
    assert "layout: $ROOT/mipnerf360/<scene>/{images,images_2,images_4,images_8}/" in text
    assert "layout: $ROOT/db/<scene>/images/ and <scene>/sparse/0/{cameras,images,points3D}.bin" in text
    assert "--from-file" in text


def test_an_experiment_on_missing_data_names_the_download_command(tmp_path, monkeypatch):
    from protocols.run import run_experiment

    empty = tmp_path / "data"
    empty.mkdir()
    args = ["+experiment=budget5", "grid.methods=[3dgs]", f"data_root={empty}", f"out_dir={tmp_path}/runs",
            "report=false"]
    with pytest.raises(SystemExit) as e:
        run_experiment(args)
    msg = str(e.value)
    assert "on_missing=skip" not in msg   # no scene is there: skipping the missing ones would run nothing
    for dataset, scene in (("mipnerf360", "bicycle"), ("tandt", "truck"), ("deepblending", "playroom")):
        assert f"get it with: smgs download {dataset} --scenes {scene} --root {empty}" in msg
    monkeypatch.chdir(tmp_path)   # the default data root, "data", is shown as the folder it names
    monkeypatch.delenv("SMGS_DATA_ROOT", raising=False)
    (tmp_path / "data").rmdir()
    with pytest.raises(SystemExit, match=rf"get it with: smgs download tandt --scenes train --root {tmp_path}/data\n"):
        run_experiment(args[:2] + ["grid.datasets=[tandt]"] + args[3:])


def test_the_hint_without_a_data_root_says_to_set_one_and_is_empty_for_other_datasets(monkeypatch):
    from protocols.cell_scene import download_hint

    monkeypatch.delenv("SMGS_DATA_ROOT", raising=False)
    assert download_hint("deepblending", "playroom", None) == (
        "; get it with: smgs download deepblending --scenes playroom --root DIR and set SMGS_DATA_ROOT=DIR")
    assert download_hint("colmap", "x", "/data") == ""


def test_ctrl_c_keeps_what_arrived_and_the_same_command_resumes(tmp_path, tandt_db, capsys, monkeypatch):
    from smgs.data.download import fetch
    from smgs_cli.main import main

    real, calls = fetch._write, []

    def interrupted(f, chunk, part):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        real(f, chunk, part)

    monkeypatch.setattr(fetch, "CHUNK", 64 * 1024)
    monkeypatch.setattr(fetch, "_write", interrupted)
    root = tmp_path / "data"
    with Server({"tandt_db.zip": tandt_db}) as srv:
        cmd = ["download", "tandt", "--root", str(root), "--mirror", srv.url]
        assert main(cmd) == 130
        assert "interrupted; what arrived is kept: rerun the same command to resume" in capsys.readouterr().err
        assert (root / STAGING / "tandt_db.zip.part").stat().st_size == 2 * 64 * 1024
        assert main(cmd) == 0
    assert srv.requests[1][1] == f"bytes={2 * 64 * 1024}-"
    assert "done: 2 scene(s) unpacked" in capsys.readouterr().out


def _stump_archive(tmp_path: Path) -> Path:
    archive = tmp_path / "hand" / "360_v2.zip"
    archive.parent.mkdir(exist_ok=True)
    archive.write_bytes(_mipnerf_archive())
    return archive


def test_the_space_check_counts_the_blocks_the_files_take_not_only_their_sizes(tmp_path, monkeypatch):
    """Free space equal to the declared sizes is not enough: each file takes whole blocks."""
    archive = _stump_archive(tmp_path)
    with zipfile.ZipFile(archive) as zf:
        declared = sum(i.file_size for i in zf.infolist() if i.filename.startswith("stump/"))
    Usage = namedtuple("Usage", "total used free")
    monkeypatch.setattr(unpack.shutil, "disk_usage", lambda p: Usage(10**12, 10**12 - declared, declared))
    root = tmp_path / "data"
    with pytest.raises(DiskSpaceError) as e:
        _get(root, _closed_port_url(), "mipnerf360", scenes=("stump",), from_file=archive)
    assert (f"not enough free space in {root / 'mipnerf360'}: unpacking stump from 360_v2.zip needs "
            f"{unpack.human_size(unpack.footprint(_members(archive, 'stump/'), unpack._block_size(root)))}, "
            f"{unpack.human_size(declared)} are free") in str(e.value)
    assert unpack.footprint(_members(archive, "stump/"), 4096) > 125 * 4 * 4096   # 500 images, a block each at least
    assert _leftovers(root) == [] and not (root / "mipnerf360" / "stump").exists()


def _members(archive: Path, prefix: str) -> list[zipfile.ZipInfo]:
    with zipfile.ZipFile(archive) as zf:
        return [i for i in zf.infolist() if i.filename.startswith(prefix) and not i.is_dir()]


def test_a_disk_that_fills_up_while_unpacking_says_how_much_is_needed_and_where(tmp_path, monkeypatch):
    import errno

    archive = _stump_archive(tmp_path)
    given = archive.read_bytes()   # as made (a zip made again later carries another time stamp)
    real, calls = unpack.shutil.copyfileobj, []

    def filling(src, dst, length=0):
        calls.append(1)
        if len(calls) > 40:   # another writer took the space after the check
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(src, dst, length)

    monkeypatch.setattr(unpack.shutil, "copyfileobj", filling)
    root = tmp_path / "data"
    with pytest.raises(DiskSpaceError) as e:
        _get(root, _closed_port_url(), "mipnerf360", scenes=("stump",), from_file=archive)
    msg = str(e.value)
    need = unpack.human_size(unpack.footprint(_members(archive, "stump/"), unpack._block_size(root)))
    assert (f"the disk holding {root / 'mipnerf360'} filled up while unpacking stump from 360_v2.zip (No space left "
            f"on device): it needs about {need} there, ") in msg
    assert "are free now; the partial folder was removed" in msg and "--root DIR" in msg and "\n" not in msg
    assert _leftovers(root) == [] and not (root / "mipnerf360" / "stump").exists()
    assert archive.read_bytes() == given, "the user's archive is untouched"


@pytest.mark.parametrize("file_first", [True, False], ids=["file-then-folder", "folder-then-file"])
def test_an_archive_with_a_file_where_a_folder_must_be_is_refused_naming_both(tmp_path, file_first):
    files = scene_files(125, MIP_FOLDERS)
    files = {"sparse": b"not a folder", **files} if file_first else {**files, "sparse": b"not a folder"}
    archive = tmp_path / "360_v2.zip"
    archive.write_bytes(zip_bytes({"stump/": files}))
    root = tmp_path / "data"
    with pytest.raises(ArchiveError) as e:
        _get(root, _closed_port_url(), "mipnerf360", scenes=("stump",), from_file=archive)
    msg = str(e.value)
    assert "360_v2.zip holds stump/sparse as a file and also stump/sparse/0/" in msg
    assert "a file where a folder must be" in msg and f"{archive} is not the 360_v2.zip its authors publish" in msg
    assert _leftovers(root) == [] and not (root / "mipnerf360" / "stump").exists()


@pytest.mark.parametrize("honest_ranges", [False, True], ids=["lies-on-resume-too", "range-says-the-real-size"])
def test_a_server_whose_content_length_is_too_long_is_named_instead_of_a_rerun_forever(tmp_path, tandt_db,
                                                                                       honest_ranges):
    root, n = tmp_path / "data", len(tandt_db)
    with Server({"tandt_db.zip": tandt_db}) as srv:
        srv.overstate["tandt_db.zip"], srv.honest_ranges = 1000, honest_ranges
        with pytest.raises(NetworkError, match=rf"ended at byte {n} of {n + 1000}; rerun the same command"):
            _get(root, srv.url, "tandt")   # once, it looks like a broken connection
        for _ in range(2):   # then it is named, and stays named
            with pytest.raises(RemoteChangedError) as e:
                _get(root, srv.url, "tandt")
            msg = str(e.value)
            assert (f"/tandt_db.zip declares the archive as {n + 1000} bytes (Content-Length) but sends nothing past "
                    f"byte {n}, on two tries alike: its size is misreported") in msg
            assert "a rerun would fail the same way" in msg and "rerun the same command" not in msg
            assert f"--root {root} --from-file /path/to/tandt_db.zip" in msg
    assert (root / STAGING / "tandt_db.zip.part").read_bytes() == tandt_db, "what arrived is kept"


def test_a_transfer_broken_twice_at_different_bytes_still_resumes(tmp_path, tandt_db):
    root = tmp_path / "data"
    with Server({"tandt_db.zip": tandt_db}) as srv:
        for cut in (1000, 5000):
            srv.cut_after["tandt_db.zip"] = cut
            with pytest.raises(NetworkError, match="rerun the same command to resume"):
                _get(root, srv.url, "tandt")
        assert _get(root, srv.url, "tandt")[0].unpacked == ["tandt/train", "tandt/truck"]


@pytest.mark.parametrize("content", ["notes", "incomplete zip", "damaged member"])
def test_from_file_of_the_wrong_file_never_says_to_delete_it(tmp_path, capsys, monkeypatch, content):
    from smgs_cli.main import main

    given = tmp_path / "notes.txt"
    if content == "notes":
        given.write_text("my own notes, not an archive\n")
    elif content == "incomplete zip":
        given.write_bytes(zip_bytes({"tandt/train/": scene_files(301, registered=300)}))
    else:
        good = zip_bytes({"tandt/train/": scene_files(301)})
        with zipfile.ZipFile(io.BytesIO(good)) as zf:
            info = zf.getinfo("tandt/train/images/frame_00042.jpg")
            at = info.header_offset + 30 + len(info.filename) + len(info.extra) + 2
        given.write_bytes(good[:at] + bytes([good[at] ^ 0xFF]) + good[at + 1:])
    before = given.read_bytes()
    monkeypatch.delenv("SMGS_DATA_ROOT", raising=False)
    root = tmp_path / "data"
    assert main(["download", "tandt", "--scenes", "train", "--root", str(root), "--from-file", str(given)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("smgs download: ") and err.count("\n") == 1, err
    assert "delete" not in err.lower(), err
    assert (f"{given} is not the tandt_db.zip its authors publish "
            "(https://repo-sam.inria.fr/fungraph/3d-gaussian-splatting/datasets/input/tandt_db.zip); pass that "
            f"archive with --from-file, or leave --from-file out to download it ({given} is left as it is)") in err
    assert given.read_bytes() == before and _leftovers(root) == []
