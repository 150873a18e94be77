"""``python -m protocols.evaluate_ply MODEL.ply [key=value ...]``: score a model trained elsewhere (a
3DGS PLY: the original code's ``point_cloud/iteration_30000/point_cloud.ply``, gsplat's
``export_splats``, nerfstudio's ``ns-export gaussian-splat``) under this harness's protocol.

The key=value overrides are those of ``protocols.run`` (``dataset=``, ``scene=``, ``protocol=``,
``data_root=``, ``experiment_name=``, ``eval.*``, ``backend=``). The method follows from the file
(``3dgs`` without Softmax-GS extras); the budget is ``pretrained``. The test views are rendered
exactly as for a trained run (same split, resolution rule, 8-bit quantisation, metrics, FPS,
renders) by the same code, with zero training steps; ``results.json`` lands in
``<out_dir>/<dataset>/<scene>/<method>/pretrained/seed<seed>/`` and records the file (path,
sha256, header) under ``source`` with ``trained_here: false``. With ``report=true`` (default) the
experiment's report is rebuilt, the pretrained row beside the trained ones.
"""

from __future__ import annotations

import sys
from pathlib import Path

from protocols.grid import PRETRAINED as BUDGET, Cell

USAGE = """usage: smgs evaluate MODEL.ply [KEY=VALUE ...] [--force]
       (python -m protocols.evaluate_ply, the same arguments)

Score a 3DGS PLY trained elsewhere under this harness's protocol: its test views rendered and scored
as a trained run's, with zero training steps; results.json lands in
<out_dir>/<dataset>/<scene>/<method>/pretrained/seed<seed>/.

arguments:
  MODEL.ply               the model: the original 3DGS code's point_cloud.ply, gsplat's export_splats,
                          nerfstudio's ns-export gaussian-splat, or `smgs export`'s
  KEY=VALUE               overrides of `smgs run`'s config (configs/config.yaml), among them:
    dataset=NAME            the scene's kind (smgs list datasets): colmap, transforms, mipnerf360, ...
    dataset.path=DIR        the scene's folder (dataset=colmap or transforms)
    scene=NAME              which scene of a dataset that holds several
    protocol=NAME           cpu (default) or paper (smgs list protocols)
    data_root=DIR           where the named datasets live (default $SMGS_DATA_ROOT, else data)
    out_dir=DIR             the results root (default runs/<experiment_name>)
    experiment_name=NAME    the experiment whose report gets the row (default: default)
    eval.KEY=VALUE          evaluation settings, e.g. eval.flip=false, eval.fps_repeats=2
    device=auto|cpu|cuda[:N], backend=auto|cpu|cuda|reference
    report=false            leave the experiment's report as it is
    budget.name=pretrained-NAME   a cell (and report row) of its own, for a second model of the same
                            scene: another file is refused in a cell that holds one's evaluation
  --force                 score it again though the same file and config were scored before, or
                          replace the evaluation of another file in its cell
  -h, --help              this text

The method follows from the file (3dgs without Softmax-GS extras: method= is not needed); the
budget is pretrained. docs/ply.md has the details."""


def evaluation_config(ply: Path, overrides: list[str]) -> dict:
    """The resolved cell config that evaluates ``ply`` (Hydra composed from configs/). The scene is
    ``scene=``, else the dataset's one scene, named as ``smgs run`` names it (a folder given by
    ``dataset.path`` is its one scene, named after it); a dataset of several needs ``scene=``."""
    from hydra import initialize_config_dir
    from omegaconf import OmegaConf

    from protocols.ply import read_scored_ply, sha256
    from protocols.run import CONFIG_DIR, _method_overrides, _scenes_of, compose_checked

    mode = read_scored_ply(ply).mode   # bad input stops here, before anything is composed or written
    for o in overrides:
        if o.startswith("method=") and o.split("=", 1)[1] != mode:
            raise ValueError(f"{ply} holds a {mode} model; it cannot be evaluated as {o.split('=', 1)[1]!r} "
                             "(leave method= out)")
        if o.startswith(("budget=", "grid.")):
            raise ValueError(f"{o}: an evaluated PLY has budget {BUDGET!r} and no grid")
    fixed = [o for o in overrides if not o.startswith(("method=", "method.name="))]
    fixed += _method_overrides(mode) + [f"budget={BUDGET}"]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = OmegaConf.to_container(compose_checked(fixed), resolve=True)
        if cfg.get("scene") is None:
            scenes = _scenes_of(str(cfg["dataset"]["name"]), fixed)
            if len(scenes) != 1:
                raise ValueError(f"dataset {cfg['dataset']['name']!r} holds {len(scenes)} scenes ({', '.join(scenes)}): "
                                 "name the one the model shows with scene=NAME")
            cfg = OmegaConf.to_container(compose_checked(fixed + [f"scene={scenes[0]}"]), resolve=True)
    cfg["ply"] = {"path": str(ply.resolve()), "sha256": sha256(ply)}
    return cfg


def evaluate_ply(ply: Path | str, overrides: list[str]) -> dict:
    """Evaluate one PLY; returns ``run_cell``'s summary plus the run directory. The cell holds one
    file's evaluation: another file of the same scene is refused there (``protocols.cell``) unless
    it gets a budget name of its own (``budget.name=pretrained-NAME``) or ``--force`` replaces it."""
    from protocols.cell import run_cell
    from protocols.cell_scene import check_available
    from protocols.grid import check_path_names

    ply = Path(ply)
    cfg = evaluation_config(ply, overrides)
    missing = check_available(cfg)
    if missing:
        raise FileNotFoundError(f"missing data: {missing}")
    cell = Cell(cfg["method"]["name"], cfg["dataset"]["name"], str(cfg["scene"]), str(cfg["budget"]["name"]),
                int(cfg["seed"]))
    check_path_names(str(cfg.get("experiment_name", "")), [cell])
    run_dir = Path(cfg["out_dir"]) / cell.key
    summary = run_cell({"key": cell.key, "run_dir": str(run_dir), "config": cfg})
    summary["run_dir"] = str(run_dir)
    if cfg.get("report"):
        from protocols.report_step import build_report

        summary["report"] = str(build_report(Path(cfg["out_dir"]), cfg.get("report_builder")))
    return summary


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if "--force" in argv:
        argv = [a for a in argv if a != "--force"] + ["force=true"]
    if "-h" in argv or "--help" in argv:
        print(USAGE)
        return 0
    from protocols.ply import is_ply_argument

    plys = [a for a in argv if is_ply_argument(a)]
    if len(plys) != 1:
        what = "no model given" if not plys else f"one model at a time, got {len(plys)}: {' '.join(plys)}"
        print(f"{USAGE}\n\nerror: {what}", file=sys.stderr)
        return 2
    from protocols.refused import EXIT_REFUSED, Refused

    try:
        s = evaluate_ply(plys[0], [a for a in argv if not is_ply_argument(a)])
    except Refused as e:
        print(f"error: {e.message}", file=sys.stderr)
        return EXIT_REFUSED
    except (OSError, ValueError) as e:   # the model, the scene or a setting: nothing was run
        print(f"error: {e}", file=sys.stderr)
        return EXIT_REFUSED
    if s["status"] != "ok":
        print(f"error: {s['key']}: {s['status']}: {s.get('error')}", file=sys.stderr)
        return 1
    what = "already evaluated (same file and config; --force redoes it)" if s.get("skipped") else \
        f"PSNR {s['psnr']:.2f}"
    print(f"{s['run_dir']}/results.json: {what}")
    if s.get("report"):
        print(f"report: {s['report']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
