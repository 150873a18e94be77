"""The saved images of the runs, found on disk, as the data of report.html's viewers.

Per run directory (``protocols.view_images``): ``renders/<view>.png`` (every test view),
``renders/gt/<view>.png`` and ``renders/error/<view>.png`` (a few views), ``consistency/strip.png``
with ``strip.json``. Paths go into the page relative to the report's directory; nothing is copied.
"""

from __future__ import annotations

import json
import os
from collections import defaultdict
from pathlib import Path

from reports.html.escape import rel_url
from reports.html.figures import run_name
from reports.paper import budget_rank, dataset_rank, method_label, method_rank, scene_rank
from reports.runs import Run, budget_label

MAX_VIEWS = 6   # views offered per scene: the ones with ground truth saved, else the first renders


def _pngs(folder: Path) -> dict[str, Path]:
    try:
        with os.scandir(folder) as it:
            return {Path(e.name).stem: Path(e.path) for e in it if e.name.endswith(".png") and e.is_file()}
    except OSError:
        return {}


def viewers(runs: list[Run], runs_dir: Path, out: Path) -> list[dict]:
    """One viewer per scene with saved renders: its views, the ground truth of each, and per
    configuration (budget, preset, seed) each method's render, |error| map and view PSNR."""
    scenes: dict[tuple[str, str], list[tuple[Run, dict, dict, dict]]] = defaultdict(list)
    for run in runs:
        if run.r.status != "ok":
            continue
        d = run.path.parent / "renders"
        renders = _pngs(d)
        if renders:
            scenes[(run.r.dataset, run.r.scene)].append((run, renders, _pngs(d / "gt"), _pngs(d / "error")))
    out_list = []
    for k, ((ds, scene), items) in enumerate(sorted(scenes.items(), key=lambda kv: (dataset_rank(kv[0][0]),
                                                                                    scene_rank(*kv[0])))):
        gt: dict[str, Path] = {}
        for _, _, g, _ in items:
            for stem, p in g.items():
                gt.setdefault(stem, p)
        if gt:
            views = sorted(gt)[:MAX_VIEWS]
        else:
            views = sorted(items[0][1])[:MAX_VIEWS]
        groups: dict[tuple, list[dict]] = defaultdict(list)
        for run, renders, _, errors in items:
            r = run.r
            psnr = _view_psnr(r.per_view)
            groups[(budget_label(run.r), r.preset, r.seed)].append({
                "method": method_label(r.method), "key": r.method, "run": run_name(run, runs_dir),
                "render": {v: rel_url(renders[v], out) for v in views if v in renders},
                "error": {v: rel_url(errors[v], out) for v in views if v in errors},
                "psnr": {v: psnr[v] for v in views if v in psnr}})
        out_list.append({"id": f"viewer-{k}", "scene": f"{ds}/{scene}", "views": views,
                         "gt": {v: rel_url(gt[v], out) for v in views if v in gt},
                         "groups": by_configuration(groups, "runs"),
                         "note": "" if gt else "These runs saved no ground truth or |error| maps (runs made before "
                                               "eval.viewer_views existed): renders only."})
    return out_list


def by_configuration(groups: dict[tuple, list[dict]], what: str) -> list[dict]:
    """One scene's entries (a viewer's runs, a player's videos) grouped by (budget, preset, seed), in the
    report's order (budget, the paper's preset first, seed), each group labelled "budget · seed s" (and
    "· [preset]") with its entries under ``what``, in the methods' order."""
    out = []
    for (budget, preset, seed), entries in sorted(groups.items(), key=lambda kv: (
            budget_rank(kv[0][0]), kv[0][1] != "paper", kv[0][1], kv[0][2])):
        entries.sort(key=lambda x: method_rank(x["key"]))
        out.append({"label": f"{budget} · seed {seed}" + ("" if preset == "paper" else f" · [{preset}]"), what: entries})
    return out


def _view_psnr(per_view: dict) -> dict[str, float]:
    names, vals = per_view.get("name") or [], per_view.get("psnr") or []
    out = {}
    for n, v in zip(names, vals):
        if isinstance(v, (int, float)):
            out[Path(str(n)).stem] = float(v)
    return out


def strips(runs: list[Run], runs_dir: Path, out: Path) -> list[dict]:
    """The popping strips of the runs that saved one: frames i … i+step around the worst pair."""
    found = []
    for run in runs:
        d = run.path.parent / "consistency"
        png = d / "strip.png"
        if run.r.status != "ok" or not png.is_file():
            continue
        try:
            info = json.loads((d / "strip.json").read_text())
        except (OSError, ValueError):
            info = {}
        found.append((run, png, info if isinstance(info, dict) else {}))
    found.sort(key=lambda t: (dataset_rank(t[0].r.dataset), scene_rank(t[0].r.dataset, t[0].r.scene),
                              method_rank(t[0].r.method), budget_rank(budget_label(t[0].r)), t[0].r.seed))
    return [{"scene": f"{run.r.dataset}/{run.r.scene}", "method": method_label(run.r.method), "run": run_name(run, runs_dir),
             "src": rel_url(png, out), "frames": info.get("frames"), "mse": info.get("mse"), "why": info.get("why", "")}
            for run, png, info in found]
