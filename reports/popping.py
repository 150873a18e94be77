"""Popping at a depth-order flip, next to Table 4's averaged numbers: the popping ratio of every
method on the synthetic flip scenes (``smgs.metrics.consistency.popping``) and strips of frames
around the flip.

In a report it appears with Table 4 (runs that computed view consistency); alone:
``python -m reports.popping OUT_DIR`` writes ``popping.md``, ``popping.csv`` and the strips.
"""

from __future__ import annotations

import csv
import io
import sys

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from protocols.results import RunResult
from smgs.atomic import atomic_write_bytes, atomic_write_text
from smgs.metrics.consistency.popping import POP_METHODS, PopResult, flip_scenes, orbit_path, popping_table
from reports.plots import Plot
from reports.runs import Value
from reports.table_model import Column, Row, Section, Table, fixed

STRIP_SCENES = ("crossing_30", "coplanar_pair")
STRIP_FRAMES = (-1, 0, 1, 2)   # frames around the flip pair (k, k+1)


def wants_popping(runs: list[RunResult]) -> bool:
    """Whether a report shows the popping section: where Table 4 has rows."""
    return any(r.consistency for r in runs)


def _strip(scene: str, results: list[PopResult], frames: dict[tuple[str, str], list[torch.Tensor]]) -> Plot:
    methods = [m.name for m in POP_METHODS if (scene, m.name) in frames]
    k = next(r.flip_index for r in results if r.scene == scene)
    idx = [k + d for d in STRIP_FRAMES]
    fig = Figure(figsize=(1.6 * len(idx) + 1.6, 1.25 * len(methods) + 0.4), dpi=100)
    ratio = {r.method: r.ratio for r in results if r.scene == scene}
    for i, m in enumerate(methods):
        for j, f in enumerate(idx):
            ax = fig.add_subplot(len(methods), len(idx), i * len(idx) + j + 1)
            ax.imshow(np.clip(frames[(scene, m)][f].float().numpy(), 0, 1), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(f"frame {f}" + (" | flip" if f == k else ""), fontsize=7)
            if j == 0:
                ax.set_ylabel(f"{m}\n×{ratio[m]:.3g}", fontsize=7)
    fig.suptitle(f"{scene}: frames around the depth-order flip (between frames {k} and {k + 1})", fontsize=8)
    buf = io.BytesIO()
    FigureCanvasAgg(fig).print_png(buf)
    return Plot(f"popping_{scene}.png", f"{scene}: frames {idx[0]}–{idx[-1]} of the orbit for every method; the "
                f"centres' depth order flips between frames {k} and {k + 1}; ×ratio per row.", buf.getvalue())


def popping_section(runs: list[RunResult] | None = None) -> tuple[Section, list[Plot]]:
    """The section and its strips (renders the scenes: about ten seconds on a CPU)."""
    sec = Section("popping", "Popping at a depth-order flip (next to Table 4)")
    if runs is not None and not wants_popping(runs):
        sec.empty_reason = "shown with Table 4 only (no run computed view consistency); `python -m reports.popping DIR`"
        return sec, []
    cams = orbit_path()
    results, frames = popping_table(cameras=cams, keep_frames=True)
    scenes = flip_scenes()
    sec.intro.append(
        f"Table 4 averages the warped error over all frame pairs, so the few pairs where a depth order flips are "
        f"diluted. Here each synthetic scene is rendered along an orbit of {len(cams)} frames that crosses the flip "
        f"of its splats' centre depths once, between the two middle frames; the ratio is the frame-to-frame change "
        f"there (mean over pixels of the squared RGB difference) over the median change between the other "
        f"consecutive frames. 1 = no pop. Fixed splats, not trained models: every method renders the same ones "
        f"(reference renderer, float64).")
    methods = [m.name for m in POP_METHODS]
    cols = [Column(m, m, fixed(2)) for m in methods]
    by = {(r.scene, r.method): r for r in results}
    rows = [Row([name], {m: Value.of(by[(name, m)].ratio) for m in methods}, csv={"scene": name})
            for name in scenes]
    notes = [f"{s.name}: {s.description}" for s in scenes.values()]
    notes.append("Methods: " + "; ".join(
        f"{m.name} = mode {m.mode}, sort {m.sort}" + (f", α {m.alpha:g}" if m.mode in ("gef_only", "softmax_gs") else "")
        + (f", β {m.beta:g}, γ {m.gamma:g}" if m.mode in ("softmax_only", "softmax_gs") else "") for m in POP_METHODS))
    sec.blocks.append(Table("", ["Scene"], cols, rows, notes=notes, rank="none"))
    return sec, [_strip(s, results, frames) for s in STRIP_SCENES]


def main(argv: list[str] | None = None) -> int:
    from reports.commands import popping_parser

    args = popping_parser().parse_args(argv)
    sec, plots = popping_section()
    args.out.mkdir(parents=True, exist_ok=True)
    md = sec.markdown() + "\n" + "\n".join(f"![{p.caption}]({p.name})\n" for p in plots)
    for p in plots:
        atomic_write_bytes(args.out / p.name, p.png)
    recs = sec.csv_records()
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(recs[0]))
    w.writeheader()
    w.writerows(recs)
    atomic_write_text(args.out / "popping.csv", buf.getvalue())
    atomic_write_text(args.out / "popping.md", md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
