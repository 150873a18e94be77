"""Videos: the encoder (PyAV, VP9 in WebM) keeps frame count and loses little; a run with view
consistency encodes the frames its metric rendered; ``smgs render`` puts runs of one scene side by side
and refuses what it cannot show; report.html plays the videos in step in headless Chromium.

Cost (2 busy cores): the tree of 3 tiny smoke runs and a 2D-pattern run ~20 s, the report ~5 s,
``smgs render`` ~5 s, the browser ~10 s."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from protocols.results import RunResult, read_result, write_result
from smgs.io.video import VideoWriter, encoded_size, max_bytes_per_second, read_video, shrink

try:
    from browser import Browser, find_chromium

    CHROMIUM, CHROMIUM_REASON = find_chromium()
except ImportError as e:  # pragma: no cover
    CHROMIUM, CHROMIUM_REASON = None, str(e)
needs_browser = pytest.mark.skipif(CHROMIUM is None, reason=f"browser test skipped: {CHROMIUM_REASON}")

SMOKE = ["+experiment=smoke", "grid.methods=[3dgs,softmax_gs]", "grid.seeds_of={3dgs:[0,1],softmax_gs:[0]}", "report=false",
         "protocol.steps=5", "dataset.width=96", "dataset.height=72", "dataset.n_views=10", "eval.consistency=true",
         "eval.fps_repeats=1", "eval.flip=false"]
PATTERN = ["+experiment=patterns", "grid.methods=[3dgs]", "grid.budgets=[cap4]", "grid.seeds=[0]",
           "grid.scenes=[circle4]", "dataset.size=16", "dataset.steps=12", "report=false", "eval.fps_repeats=1",
           "eval.flip=false"]
MIN_PSNR = 35.0   # the codec's loss a frame may carry (dB)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(255.0 ** 2 / mse)


def smooth_frames(n: int, w: int, h: int) -> list[np.ndarray]:
    """A moving colour gradient with a soft disc: what a flythrough of a splat model looks like."""
    y, x = np.mgrid[0:h, 0:w] / max(w, h)
    out = []
    for k in range(n):
        d = np.exp(-((x - 0.3 - 0.02 * k) ** 2 + (y - 0.4) ** 2) / 0.02)
        img = np.stack([0.2 + 0.6 * x, 0.3 + 0.4 * y, 0.5 + 0.4 * d], -1)
        out.append((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
    return out


# ---- the encoder --------------------------------------------------------------------------------

def test_a_video_keeps_every_frame_within_the_codecs_loss(tmp_path):
    frames = smooth_frames(20, 41, 30)
    with VideoWriter(tmp_path / "v.webm", 41, 30) as v:
        for f in frames:
            v.add(f)
        info = v.close()
    assert (info.width, info.height, info.scale) == encoded_size(41, 30) == (288, 210, 7)   # enlarged 7x, padded to even sides
    got, fps = read_video(tmp_path / "v.webm")
    assert len(got) == info.frames == 20 and fps == 30 and got[0].shape == (210, 288, 3)
    assert min(psnr(shrink(g, 41, 30), f) for g, f in zip(got, frames)) >= MIN_PSNR
    assert info.bytes == (tmp_path / "v.webm").stat().st_size
    assert info.bytes_per_second <= 1.2 * max_bytes_per_second(41, 30)   # the ceiling is on the average rate
    assert [p.name for p in tmp_path.iterdir()] == ["v.webm"]   # no temporary file left


def test_an_error_while_writing_leaves_the_previous_file(tmp_path):
    path = tmp_path / "v.webm"
    path.write_bytes(b"previous")
    with pytest.raises(ValueError, match=r"frame 1 is uint8 \(10, 10, 3\), expected uint8 \(30, 40, 3\)"):
        with VideoWriter(path, 40, 30) as v:
            v.add(smooth_frames(1, 40, 30)[0])
            v.add(np.zeros((10, 10, 3), np.uint8))
    assert path.read_bytes() == b"previous" and [p.name for p in tmp_path.iterdir()] == ["v.webm"]


def test_frames_given_out_of_order_are_written_in_order(tmp_path):
    from smgs.io.flythrough import ERRORS, FRAMES, FlythroughTap

    frames = [np.full((30, 40, 3), 20 * k, np.uint8) for k in range(6)]   # flat frames: 0, 20, 40, ...
    tap = FlythroughTap(tmp_path / "video", 6, 40, 30, step=2)
    for k in (0, 1, 2, 4, 3, 5):   # as the metric's window renders them
        tap.frame(k, frames[k].astype(np.float32) / 255)
        if k >= 2:   # the pair (k - 2, k), warped with a flow of zero
            tap.pair(k - 2, k, frames[k - 2] / 255.0, frames[k] / 255.0, np.ones((30, 40), bool))
    rec = tap.finish()
    assert rec["frames"] == 6 and rec["frames_file"] == f"video/{FRAMES}" and rec["error_file"] == f"video/{ERRORS}"
    got, _ = read_video(tmp_path / "video" / FRAMES)
    assert [round(float(g.mean()) / 20) for g in got] == [0, 1, 2, 3, 4, 5]
    errs, _ = read_video(tmp_path / "video" / ERRORS)
    assert len(errs) == 6 and float(errs[1][..., 1].mean()) < 12 and float(errs[5][..., 0].mean()) > 100   # red: error


def test_a_failure_to_write_stops_the_video_not_the_scoring(tmp_path, monkeypatch):
    from smgs.io.flythrough import FlythroughTap

    tap = FlythroughTap(tmp_path / "video", 4, 40, 30, step=2)
    tap.frame(0, np.zeros((30, 40, 3), np.float32))

    def full_disk(frame):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(tap.frames, "add", full_disk)
    for k in (1, 2, 3):
        tap.frame(k, np.zeros((30, 40, 3), np.float32))   # no error reaches the metric
    with pytest.raises(RuntimeError, match="could not be written .OSError: .Errno 28. No space left on device"):
        tap.finish()
    assert list((tmp_path / "video").iterdir()) == []


# ---- runs, smgs render, the report --------------------------------------------------------------

@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    from protocols.run import run_experiment
    from reports.build import build_report

    root = tmp_path_factory.mktemp("video") / "runs"
    assert [s["status"] for s in run_experiment(SMOKE + [f"out_dir={root}"])] == ["ok"] * 3
    assert [s["status"] for s in run_experiment(PATTERN + [f"out_dir={root}"])] == ["ok"]
    build_report(root, stability="skipped")
    return root


def smoke_run(root: Path, method: str = "3dgs", seed: int = 0) -> Path:
    return root / f"procedural/blocks/{method}/full/seed{seed}"


def test_a_run_encodes_the_frames_its_consistency_metric_rendered(tree):
    from protocols.run_video import read_trajectory

    run = smoke_run(tree)
    r = read_result(run / "results.json")
    v = r.consistency["video"]
    n = len(read_trajectory(run / "trajectory.json"))
    assert n == r.consistency["trajectory"]["n_frames"] == v["frames"] == 48
    for key in ("frames_file", "error_file"):
        frames, fps = read_video(run / v[key])
        assert len(frames) == n and fps == v["fps"] == 30
    # the poster is frame 0 exactly as the metric quantised it (PNG, lossless); the video's is within the codec's loss
    poster = np.asarray(Image.open(run / v["poster"]).convert("RGB"))
    first = read_video(run / v["frames_file"])[0][0]
    got = psnr(shrink(first, 96, 72), poster)
    print(f"run video: first frame {got:.1f} dB against the metric's frame, {v['bytes_per_second'] / 2e3:.1f} kB/s a video")
    assert poster.shape == (72, 96, 3) and got >= MIN_PSNR
    assert v["bytes"] > 0 and v["seconds"] > 0 and 0 < v["seconds"] < r.diagnostics["run_seconds"]


def test_smgs_render_puts_runs_of_one_scene_side_by_side(tree, tmp_path, capsys):
    from protocols.render_video import Mosaic, finished_run, path_cameras, rebuild
    from smgs.metrics.image import to_uint8
    from smgs_cli.main import main

    runs = [smoke_run(tree, "3dgs"), smoke_run(tree, "softmax_gs")]
    out = tmp_path / "blocks.webm"
    assert main(["render", *map(str, runs), "--out", str(out)]) == 0
    assert f"{out}: 48 frames" in capsys.readouterr().out
    frames, _ = read_video(out)
    fr = [finished_run(r) for r in runs]
    method, scene = rebuild(fr[0], "cpu")
    cams = path_cameras(fr[0], scene, "trajectory")
    assert len(frames) == len(cams) == 48   # the trajectory's frames, each once
    mosaic = Mosaic([f.label() for f in fr], cams[0].width, cams[0].height)
    for i, run in enumerate(fr):
        m = method if i == 0 else rebuild(run, "cpu")[0]
        want = to_uint8(m.render(cams[0]).rgb.clamp(0, 1)).numpy()
        x, y, w, h = mosaic.box(i)
        got = psnr(shrink(frames[0][y:y + h, x:x + w], cams[0].width, cams[0].height), want)
        print(f"smgs render, tile {i}: first frame {got:.1f} dB against the renderer's frame")
        assert got >= MIN_PSNR
    # the test views in order
    assert main(["render", str(runs[0]), "--path", "test", "--out", str(tmp_path / "test.webm")]) == 0
    assert len(read_video(tmp_path / "test.webm")[0]) == len(scene.test)


def test_smgs_render_refuses_what_it_cannot_show(tree, tmp_path, capsys):
    from smgs_cli.main import main

    run = smoke_run(tree)
    other = tmp_path / "other"
    other.mkdir()
    shutil.copy(run / "checkpoint.json", other)
    r = read_result(run / "results.json")
    r.scene = "elsewhere"
    write_result(other, r)
    failed = tmp_path / "failed"
    write_result(failed, RunResult("3dgs", "procedural", "blocks", "full", 0, status="failed", error="boom"))
    unfinished = tmp_path / "unfinished"
    unfinished.mkdir()
    pattern = tree / "patterns/circle4/3dgs/cap4/seed0"
    cases = [([run, other], "different scenes"), ([unfinished], "unfinished run (no results.json"),
             ([failed], "the run is failed (boom): it has no final model to render"),
             ([pattern], "no video trajectory: the scene circle4 is flat")]
    for dirs, message in cases:
        assert main(["render", *map(str, dirs), "--out", str(tmp_path / "x.webm")]) == 2   # refused
        err = capsys.readouterr().err
        assert err.startswith("error: ") and message in err and err.count("\n") == 1, err
    assert not (tmp_path / "x.webm").exists()


def test_the_report_says_why_a_run_has_no_video(tree):
    html = (tree / "report" / "report.html").read_text()
    assert "patterns/circle4: 1 run without a video (patterns/circle4/3dgs/cap4/seed0): view consistency: off " \
           "(eval.consistency=false); `smgs render RUN_DIR` renders its video" in html
    data = json.loads(html.split('id="report-data">', 1)[1].split("</script>", 1)[0])
    (player,) = data["players"]
    assert player["scene"] == "procedural/blocks" and player["frames"] == 48
    assert [[v["key"] for v in g["videos"]] for g in player["groups"]] == [["3dgs", "softmax_gs"], ["3dgs"]]
    assert "Encoding both videos took" in html and "media-src 'self' file: blob:" in html


# ---- in a browser -------------------------------------------------------------------------------

VIDEOS = "[...document.querySelectorAll('#{p} video')]"
WATCH = """(() => { const vs = VIDEOS; vs.forEach(v => { const t0 = v.currentTime; v.__moved = false;
  v.addEventListener('timeupdate', () => { if (Math.abs(v.currentTime - t0) > 0.05) v.__moved = true; }); });
  return vs.length; })()"""


def at_frame(p: str, k: int, fps: int) -> str:
    """Every video of the player shows frame k, seeked and ready, and the timeline says k."""
    t = (k + 0.5) / fps
    return (f"{VIDEOS.format(p=p)}.every(v => Math.abs(v.currentTime - {t}) < 1e-3 && !v.seeking && v.readyState >= 2)"
            f" && document.querySelector('#{p} input.scrub').value === '{k}'")


def check_player(b, p: str, n: int, fps: int, group: int) -> int:
    """Load, play, advance, pause, scrub and strip-seek every video of one configuration of a player."""
    b.eval(f"(() => {{ const s = document.querySelector('#{p} select'); s.value = '{group}'; "
           "s.dispatchEvent(new Event('change')); document.getElementById('" + p + "').scrollIntoView(); })()")
    vids = VIDEOS.format(p=p)
    b.wait_for(f"{vids}.length > 0 && {vids}.every(v => v.readyState >= 2)", timeout=90, what="every video loaded")
    count = b.eval(WATCH.replace("VIDEOS", vids))
    b.click(f"#{p} button.play")
    b.wait_for(f"{vids}.every(v => !v.paused && v.__moved)", timeout=90, what="every video playing, its time advancing")
    b.click(f"#{p} button.play")   # pause
    b.wait_for(f"{vids}.every(v => v.paused)", timeout=30, what="every video paused")
    k = n // 3
    b.eval(f"(() => {{ const r = document.querySelector('#{p} input.scrub'); r.value = '{k}'; "
           "r.dispatchEvent(new Event('input')); })()")
    b.wait_for(at_frame(p, k, fps), timeout=60, what=f"every video at frame {k} (the shared timeline)")
    # a real click on the popping strip, at the worst pair's frame
    f = int(b.eval(f"document.querySelector('#{p} canvas.popstrip').getAttribute('data-worst')"))
    assert f != k
    x, y = b.eval(f"(() => {{ const c = document.querySelector('#{p} canvas.popstrip'); c.scrollIntoView({{block: "
                  f"'center'}}); const r = c.getBoundingClientRect(); return [r.left + ({f} + 0.5) / {n} * r.width, "
                  "r.bottom - 4]; })()")
    for kind in ("mousePressed", "mouseReleased"):
        b.send("Input.dispatchMouseEvent", {"type": kind, "x": x, "y": y, "button": "left", "clickCount": 1},
               session=True)
    b.wait_for(at_frame(p, f, fps), timeout=60, what=f"every video at frame {f} (clicked on the strip)")
    b.click(f"#{p} input.error-toggle")
    assert b.eval(f"[...document.querySelectorAll('#{p} video.errors')].every(v => getComputedStyle(v).opacity === '1')")
    b.click(f"#{p} input.error-toggle")
    return count


@needs_browser
def test_the_videos_play_in_step_in_a_headless_browser(tree, tmp_path):
    html = tree / "report" / "report.html"
    data = json.loads(html.read_text().split('id="report-data">', 1)[1].split("</script>", 1)[0])
    with Browser(CHROMIUM, timeout=120) as b:
        b.open(html)
        b.wait_for("document.documentElement.getAttribute('data-report-ready') === '1'", what="the page's script")
        checked = 0
        for player in data["players"]:
            for g, group in enumerate(player["groups"]):
                checked += check_player(b, player["id"], player["frames"], player["fps"], g)
                assert checked and b.eval(f"document.querySelectorAll('#{player['id']} video').length") == \
                    2 * len(group["videos"])
        assert checked == 6   # 3dgs and softmax_gs at seed 0, 3dgs at seed 1: frames and warped error each
        b.screenshot(tmp_path / "player.png", "#player-0")
        assert b.problems() == []
