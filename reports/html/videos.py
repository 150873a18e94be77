"""The runs' flythrough videos, found on disk, as the data of report.html's video players.

A run that scored view consistency saves two videos of its trajectory's frames as the metric had
them (``protocols.run_video``, ``smgs.io.flythrough``): the frames, and the same frames with the
flow-warped error of each pair (i, i+step) over frame i+step. One player per scene and camera path
(frame count): per configuration (budget, preset, seed) the methods side by side, one control for
all, the per-frame warped MSE as a strip under the timeline. A run without a video says why.
Paths go into the page relative to the report's directory; nothing is copied.
"""

from __future__ import annotations

import math
import statistics
from collections import defaultdict
from pathlib import Path

from reports.html.escape import rel_url
from reports.html.figures import consistency_pairs, run_name
from reports.html.images import by_configuration
from reports.paper import dataset_rank, method_label, scene_rank
from reports.runs import Run, budget_label, one_line

FILES = ("frames_file", "error_file", "poster", "error_poster")
RENDER_HINT = "`smgs render RUN_DIR` renders its video from the run's model"


def why_no_video(run: Run) -> str | None:
    """Why a finished run has no video to show (None when it has one, its files on disk)."""
    r = run.r
    c = r.consistency or {}
    if not c:
        off = [p for p in (r.diagnostics or {}).get("plan", []) if str(p).startswith("view consistency: off")]
        return (off[0] if off else "view consistency was not scored") + f"; {RENDER_HINT}"
    v = c.get("video")
    if not isinstance(v, dict):
        return f"the run was made before runs saved their videos; {RENDER_HINT}"
    if "missing" in v:
        return f"no video: {one_line(str(v['missing']), 300)}"
    if not all(isinstance(v.get(k), int) and v[k] > 0 for k in ("frames", "fps")):
        return "its video record names no frame count or frame rate"
    for key in FILES:
        if not isinstance(v.get(key), str) or not (run.path.parent / v[key]).is_file():
            return f"its video file is not there ({v.get(key)!r} in the run directory)"
    return None


def _per_frame(run: Run, n_frames: int) -> list[float | None]:
    """The warped MSE of the pair ending at each frame (None where no pair ends or none is scored)."""
    out: list[float | None] = [None] * n_frames
    for p in consistency_pairs(run):
        j, mse = p.get("j"), p.get("mse")
        if isinstance(j, int) and 0 <= j < n_frames and isinstance(mse, (int, float)) and math.isfinite(mse):
            out[j] = float(mse)
    return out


def _video(run: Run, runs_dir: Path, out: Path) -> dict:
    r, v = run.r, run.r.consistency["video"]
    folder = run.path.parent
    mse = _per_frame(run, int(v["frames"]))
    scored = [(m, j) for j, m in enumerate(mse) if m is not None]
    worst = max(scored)[1] if scored else None
    run_s = (r.diagnostics or {}).get("run_seconds")
    psnr = r.metrics.get("psnr")
    return {"method": method_label(r.method), "key": r.method, "run": run_name(run, runs_dir), "budget": budget_label(run.r),
            "seed": r.seed, "psnr": psnr if isinstance(psnr, (int, float)) else None,
            "src": rel_url(folder / v["frames_file"], out), "error_src": rel_url(folder / v["error_file"], out),
            "poster": rel_url(folder / v["poster"], out), "error_poster": rel_url(folder / v["error_poster"], out),
            "width": v.get("source_width"), "height": v.get("source_height"), "mse": mse, "worst": worst,
            "seconds": v.get("seconds"), "bytes": v.get("bytes"), "bytes_per_second": v.get("bytes_per_second"),
            "share": v["seconds"] / run_s if isinstance(v.get("seconds"), (int, float)) and isinstance(run_s, (int, float))
            and run_s > 0 else None}


def players(runs: list[Run], runs_dir: Path, out: Path) -> tuple[list[dict], dict[str, list[tuple[str, str]]]]:
    """(one player per scene and camera path, {scene: [(run, why it has no video)]})."""
    found: dict[tuple, list[Run]] = defaultdict(list)
    missing: dict[str, list[tuple[str, str]]] = defaultdict(list)
    for run in runs:
        if run.r.status != "ok":
            continue
        why = why_no_video(run)
        scene = f"{run.r.dataset}/{run.r.scene}"
        if why:
            missing[scene].append((run_name(run, runs_dir), why))
            continue
        v = run.r.consistency["video"]
        found[(run.r.dataset, run.r.scene, v["frames"], v["fps"], int(v.get("step") or 7))].append(run)
    order = sorted(found, key=lambda k: (dataset_rank(k[0]), scene_rank(k[0], k[1]), k[2]))
    paths_of: dict[str, int] = defaultdict(int)
    for ds, scene, *_ in order:
        paths_of[f"{ds}/{scene}"] += 1
    return [_player(k, key, found[key], paths_of, runs_dir, out) for k, key in enumerate(order)], dict(missing)


def _player(k: int, key: tuple, runs: list[Run], paths_of: dict[str, int], runs_dir: Path, out: Path) -> dict:
    ds, scene, n_frames, fps, step = key
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for run in runs:
        groups[(budget_label(run.r), run.r.preset, run.r.seed)].append(_video(run, runs_dir, out))
    glist = by_configuration(groups, "videos")
    name = f"{ds}/{scene}" + (f" ({n_frames} frames)" if paths_of[f"{ds}/{scene}"] > 1 else "")
    return {"id": f"player-{k}", "scene": name, "frames": n_frames, "fps": fps, "step": step, "groups": glist,
            "cost": cost_line([v for g in glist for v in g["videos"]])}


def cost_line(videos: list[dict]) -> str:
    """What the runs' videos cost, as medians over the runs: encoding seconds, their share of the run, size."""
    def med(key: str) -> float | None:
        xs = [v[key] for v in videos if isinstance(v.get(key), (int, float))]
        return statistics.median(xs) if xs else None

    s, share, size, rate = med("seconds"), med("share"), med("bytes"), med("bytes_per_second")
    if s is None or size is None:
        return ""
    return (f"Encoding both videos took {s:.2f} s per run" + (f" ({100 * share:.1f} % of the run)" if share is not None
                                                               else "")
            + f" and they hold {size / 1e3:.0f} kB ({rate / 1e3:.1f} kB/s)"
            + (f" (medians over {len(videos)} runs)" if len(videos) > 1 else "") + ".")
