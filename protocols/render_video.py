"""``python -m protocols.render_video RUN_DIR [RUN_DIR ...] [--path trajectory|test] [--out FILE]``: a
finished run's model along its scene's camera path as a video (VP9 in WebM, ``smgs.io.video``); given
several runs of one scene, one video of them side by side, each labelled with its method, budget,
seed and test-view PSNR, in step frame by frame.

``--path trajectory`` (the default) follows the view-consistency video's path: the run's own
``trajectory.json`` where it scored view consistency, else the one the scene gives (its own, or
128 frames between consecutive test cameras), at most ``eval.consistency_max_width`` wide, as the
run's consistency video is; ``--path test`` shows the test views in name order. The model is the
run's last checkpoint, rebuilt with the run's config (its scene is loaded for that); frames are
8-bit, as the metrics see them.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from protocols.refused import EXIT_REFUSED

if TYPE_CHECKING:
    import numpy as np

PATHS = ("trajectory", "test")
DESCRIPTION = ("A finished run's model along its scene's camera path as a video (WebM); several runs of one scene "
               "side by side, labelled, in step frame by frame.")


@dataclass
class FinishedRun:
    run_dir: Path
    result: object      # protocols.results.RunResult
    checkpoint: Path

    @property
    def scene_key(self) -> tuple[str, str]:
        return self.result.dataset, self.result.scene

    def label(self) -> tuple[str, str]:
        """Two lines: the method; budget, seed and the test-view PSNR."""
        r = self.result
        psnr = r.metrics.get("psnr")
        return r.method, f"{r.budget} · seed {r.seed} · " + (f"{psnr:.2f} dB" if isinstance(psnr, (int, float))
                                                              else "PSNR —")


def finished_run(run_dir: Path | str) -> FinishedRun:
    """The run of ``run_dir`` if it finished (its final model is what a video shows), else a
    ValueError naming what is wrong and what to do."""
    from protocols.results import POINTER, RESULTS_FILE, read_result

    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ValueError(f"{run_dir}: no such run directory")
    res = run_dir / RESULTS_FILE
    if not res.is_file():
        raise ValueError(f"{run_dir}: unfinished run (no {RESULTS_FILE}; or not a run directory): a video shows a "
                         "finished run's final model; let it finish (run its experiment again to resume it)")
    result = read_result(res)
    if result.status != "ok":
        raise ValueError(f"{run_dir}: the run is {result.status} ({result.error or 'no error recorded'}): it has "
                         "no final model to render")
    ptr = run_dir / POINTER
    try:
        ckpt = run_dir / json.loads(ptr.read_text())["dir"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{run_dir}: the run's final checkpoint is not there ({ptr}: {type(e).__name__}: {e}); "
                         "rerun its experiment with --force to make it again") from None
    return FinishedRun(run_dir, result, ckpt)


def one_scene(runs: list[FinishedRun]) -> None:
    """Refuse runs of different scenes: they share no camera path."""
    scenes = {r.scene_key for r in runs}
    if len(scenes) > 1:
        listed = "; ".join(f"{r.run_dir}: {'/'.join(r.scene_key)}" for r in runs)
        raise ValueError(f"the runs are of {len(scenes)} different scenes ({listed}); a video puts runs of one "
                         "scene side by side: render each scene apart")


def rebuild(run: FinishedRun, device: str):
    """(the run's model, restored from its last checkpoint, and its scene), on ``device``."""
    from protocols.cell import with_device
    from protocols.cell_scene import load_scene_for
    from protocols.ply import make_method
    from protocols.results import RunResult
    from protocols.run_settings import cell_settings

    cfg = with_device({**run.result.config, "device": device})
    cfg["eval"] = {**cfg.get("eval", {}), "consistency": True}   # the scene with its video trajectory
    scene = load_scene_for(cfg)
    import torch

    scratch = RunResult(run.result.method, run.result.dataset, run.result.scene, run.result.budget, run.result.seed)
    method = make_method(cfg, cell_settings(cfg), scene, scratch, torch.device(cfg["device"]))
    method.load(run.checkpoint)
    method.prepare()
    return method, scene


def path_cameras(run: FinishedRun, scene, path: str) -> list:
    """The cameras of ``path`` for ``run`` (module docstring)."""
    from protocols.run_video import TRAJECTORY_FILE, read_trajectory, video_cameras

    if path == "test":
        if not scene.test:
            raise ValueError(f"{run.run_dir}: the scene {scene.name} has no test views")
        return [v.camera for v in scene.test]
    traj = run.run_dir / TRAJECTORY_FILE
    cams = read_trajectory(traj) if traj.is_file() else list(scene.trajectory or [])
    if not cams:
        raise ValueError(f"{run.run_dir}: no video trajectory: the scene {scene.name} is flat (one camera looking at "
                         "a plane: a 2D pattern), so there is no camera path to follow; --path test shows its test "
                         "view(s)")
    return video_cameras(cams, (run.result.config.get("eval") or {}).get("consistency_max_width"))


class Mosaic:
    """Tiles of ``width`` x ``height`` frames, enlarged ``scale`` times, at most ``COLUMNS`` a row, each
    under a label band; ``box(i)`` is where tile i's frame lies in the picture."""

    COLUMNS, BAND, GAP = 4, 36, 4
    BACKGROUND, TEXT = (24, 24, 24), (235, 235, 235)

    def __init__(self, labels: list[tuple[str, str]], width: int, height: int) -> None:
        import numpy as np
        from PIL import Image, ImageDraw, ImageFont

        from smgs.io.video import enlargement

        self.n, self.scale = len(labels), enlargement(width)
        self.tile_w, self.tile_h = width * self.scale, height * self.scale
        self.cols = min(self.n, self.COLUMNS)
        rows = -(-self.n // self.cols)
        self.width = self.cols * self.tile_w + (self.cols + 1) * self.GAP
        self.height = rows * (self.tile_h + self.BAND) + (rows + 1) * self.GAP
        canvas = Image.new("RGB", (self.width, self.height), self.BACKGROUND)
        draw, font = ImageDraw.Draw(canvas), ImageFont.load_default(size=13)
        for i, lines in enumerate(labels):
            x, y, _, _ = self.box(i)
            for k, line in enumerate(lines):
                draw.text((x + 2, y - self.BAND + 3 + 16 * k), _fit(draw, font, line, self.tile_w - 4), font=font,
                          fill=self.TEXT)
        self.background = np.asarray(canvas).copy()

    def box(self, i: int) -> tuple[int, int, int, int]:
        """(x, y, width, height) of tile i's frame in the picture."""
        r, c = divmod(i, self.cols)
        return (self.GAP + c * (self.tile_w + self.GAP), self.GAP + r * (self.tile_h + self.BAND + self.GAP) + self.BAND,
                self.tile_w, self.tile_h)

    def picture(self, frames: list) -> "np.ndarray":
        """The picture of one frame of each tile ([H, W, 3] uint8 each)."""
        out = self.background.copy()
        for i, f in enumerate(frames):
            x, y, w, h = self.box(i)
            out[y:y + h, x:x + w] = f.repeat(self.scale, 0).repeat(self.scale, 1) if self.scale > 1 else f
        return out


def _fit(draw, font, text: str, width: int) -> str:
    """``text`` cut with an ellipsis to fit ``width`` px."""
    if draw.textlength(text, font=font) <= width:
        return text
    while text and draw.textlength(text + "…", font=font) > width:
        text = text[:-1]
    return text + "…"


def render_video(run_dirs: list[Path | str], path: str = "trajectory", out: Path | str | None = None,
                 device: str = "auto", show_progress: bool = True):
    """The video of ``run_dirs`` along ``path`` (module docstring); returns its ``VideoInfo``."""
    from smgs.io.video import VideoWriter, video_unavailable

    if path not in PATHS:
        raise ValueError(f"--path {path!r}: one of {', '.join(PATHS)}")
    why = video_unavailable()
    if why:
        raise RuntimeError(f"no video can be written here: {why}")
    runs = [finished_run(d) for d in run_dirs]
    one_scene(runs)
    models = [rebuild(r, device) for r in runs]
    cameras = path_cameras(runs[0], models[0][1], path)
    out = Path(out) if out is not None else default_out(runs, path)
    mosaic = Mosaic([r.label() for r in runs], cameras[0].width, cameras[0].height)
    with VideoWriter(out, mosaic.width, mosaic.height) as video:
        _render_frames(video, mosaic, [m for m, _ in models], cameras, runs[0].result.scene, show_progress)
        return video.close()


def _render_frames(video, mosaic: Mosaic, methods: list, cameras: list, scene: str, show_progress: bool) -> None:
    import torch

    from protocols.progress import progress
    from smgs.metrics.image import to_uint8

    bar = progress(len(cameras), f"render {scene}", unit="frame", disable=not show_progress)
    with torch.no_grad():
        for cam in cameras:
            frames = [to_uint8(m.render(cam).rgb.clamp(0, 1)).cpu().numpy() for m in methods]
            video.add(mosaic.picture(frames))
            bar.update(1)
    bar.close()


def default_out(runs: list[FinishedRun], path: str) -> Path:
    """One run: ``RUN_DIR/video/render_<path>.webm``; several: ``<dataset>_<scene>_<path>.webm`` here."""
    from protocols.run_video import VIDEO_DIR

    if len(runs) == 1:
        return runs[0].run_dir / VIDEO_DIR / f"render_{path}.webm"
    ds, scene = runs[0].scene_key
    return Path(f"{ds}_{scene}_{path}.webm")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="smgs render", description=DESCRIPTION)
    ap.add_argument("run_dirs", type=Path, nargs="+", help="finished run directories, all of one scene")
    ap.add_argument("--path", choices=PATHS, default="trajectory",
                    help="the view-consistency trajectory (default) or the test views in order")
    ap.add_argument("--out", type=Path, default=None, help="the video file (.webm); default: RUN_DIR/video/"
                    "render_<path>.webm for one run, <dataset>_<scene>_<path>.webm here for several")
    ap.add_argument("--device", default="auto", help="where to render: auto (default), cpu, cuda, cuda:N")
    args = ap.parse_args(argv)
    try:
        info = render_video(args.run_dirs, args.path, args.out, args.device)
    except (OSError, ValueError) as e:   # runs that cannot give the video: refused (docs/usage.md, exit status)
        print(f"error: {e}", file=sys.stderr)
        return EXIT_REFUSED
    except RuntimeError as e:   # the rendering or the encoding failed
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"{info.path}: {info.frames} frames, {info.width} x {info.height}, {info.bytes / 1e3:.0f} kB "
          f"({info.bytes_per_second / 1e3:.1f} kB/s at {info.fps} fps)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
