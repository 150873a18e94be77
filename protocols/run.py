"""``python -m protocols.run +experiment=NAME [key=value ...] [--force]``

Expands the experiment's grid (methods × datasets/scenes × budgets × seeds), composes each cell's
config from the Hydra groups in configs/, runs the cells with the chosen executor, and builds the
report. Finished cells with the same config hash are skipped (``force=true`` or ``--force`` redoes
them); a failing cell is recorded and the sweep goes on.
"""

from __future__ import annotations

import json
import logging
import signal
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from protocols.executors import Terminated, on_sigterm
from protocols.grid import Cell, check_path_names, expand, path_name_problem
from protocols.method_defaults import register as register_method_defaults
from protocols.out_dir import composed_out_dir, out_dir_problem

log = logging.getLogger("smgs.protocols")


CONFIG_DIR = str(Path(__file__).resolve().parent.parent / "configs")
register_method_defaults()   # the built-in methods' configs take the trainer's defaults from the code (Hydra's store)
GRID_KEYS = ("method=", "dataset=", "budget=", "seed=", "seeds=", "scene=", "method.name=")


def has_config(group: str, name: str) -> bool:
    """Whether configs/<group>/<name>.yaml exists (a method, dataset or budget with a file of its own)."""
    return (Path(CONFIG_DIR) / group / f"{name}.yaml").exists()


def _method_overrides(method: str) -> list[str]:
    """A method with a yaml in configs/method/ is composed from it; a plugin-only method from
    configs/method/plugin.yaml with its name."""
    if has_config("method", method):
        return [f"method={method}"]
    return ["method=plugin", f"method.name={method}"]


def _dataset_overrides(dataset: str) -> list[str]:
    """A dataset with a yaml in configs/dataset/ is composed from it; a scene format or benchmark
    dataset registered only through the ``smgs.datasets`` entry point, from configs/dataset/plugin.yaml
    with its name as the dataset's name and kind (its settings: ``+dataset.KEY=VALUE``)."""
    if has_config("dataset", dataset):
        return [f"dataset={dataset}"]
    return ["dataset=plugin", f"dataset.name={dataset}", f"dataset.kind={dataset}"]


def _budget_group(budget: str, overrides: list[str]) -> str:
    """The budget file a cell's budget name is composed from: ``configs/budget/<name>.yaml``, or, for
    a budget made on the command line (``budget=cap4 budget.cap=N budget.name=capN``, docs/usage.md),
    the file it was made from."""
    if has_config("budget", budget):
        return budget
    base = _given(overrides, "budget")
    if base is not None and _given(overrides, "budget.name") == budget:
        return base
    raise ValueError(f"budget {budget!r} (grid.budgets) is no file in configs/budget/ ({', '.join(_budget_names())}); "
                     f"to make one, start from a file and name it: budget=cap4 budget.cap=N budget.name={budget}")


def _budget_names() -> list[str]:
    return sorted(p.stem for p in (Path(CONFIG_DIR) / "budget").glob("*.yaml"))


def _cell_config(cell: Cell, overrides: list[str]) -> dict:
    from hydra import compose

    # the user's key=value apply to every cell; the cell's own groups always win
    own = [x for o in cell.overrides()[1:] for x in (
        [f"budget={_budget_group(cell.budget, overrides)}"] if o.startswith("budget=") else
        _dataset_overrides(cell.dataset) if o.startswith("dataset=") else [o])]
    cfg = compose(config_name="config", overrides=[o for o in overrides if not o.startswith(GRID_KEYS)]
                  + _method_overrides(cell.method) + own)
    return OmegaConf.to_container(cfg, resolve=True)


def _scenes_of(dataset: str, overrides: list[str]) -> list[str]:
    from hydra import compose

    from smgs.data.registry import default_scenes

    cfg = compose(config_name="config", overrides=[o for o in overrides if not o.startswith("dataset=")]
                  + _dataset_overrides(dataset))
    ds = OmegaConf.to_container(cfg.dataset, resolve=True)
    scenes = ds.get("scenes")
    if not scenes and ds.get("path") not in (None, "???"):
        scenes = [Path(str(ds["path"])).name]  # a dataset given by its folder: the folder's name
    if not scenes:
        scenes = list(default_scenes(str(ds["kind"]), str(ds["name"])))   # a plugin's own
    if not scenes:
        raise ValueError(f"dataset {dataset!r} needs the scene's folder: add dataset.path=/path/to/scene "
                         f"(configs/dataset/{dataset}.yaml lists no scenes of its own)")
    return [str(s) for s in scenes]


def _given(overrides: list[str], key: str) -> str | None:
    """The value the command line gives ``key`` (``key=V``, ``+key=V`` or ``++key=V``; the last)."""
    value = None
    for o in overrides:
        k, sep, v = o.lstrip("+").partition("=")
        if sep and k == key:
            value = v
    return value


def _seed_given(cfg: DictConfig, overrides: list[str]) -> list[int] | None:
    """``seed=N`` on the command line: [N], also under an experiment whose ``grid.seeds`` (or
    ``grid.seeds_of``) lists other seeds, which it replaces (and says so); None when not given.
    Given with ``seeds=M`` or with a ``grid.seeds`` that is not [N], the sweep stops naming both."""
    given = _given(overrides, "seed")
    if given is None:
        return None
    try:
        n = int(given)
    except ValueError:
        raise SystemExit(f"invalid config, nothing was run: seed={given!r} is not an integer") from None
    if cfg.get("seeds") is not None:
        raise SystemExit(f"invalid config, nothing was run: seed={given} and seeds={cfg.get('seeds')} disagree; give "
                         "seed=N to run one seed, or seeds=M to run seeds 0 … M-1")
    listed = [str(x) for x in cfg.grid.seeds]
    if _given(overrides, "grid.seeds") is not None and listed != [str(n)]:
        raise SystemExit(f"invalid config, nothing was run: seed={given} and grid.seeds=[{', '.join(listed)}] "
                         "disagree; give seed=N to run one seed, or grid.seeds=[...] to run several")
    seeds_of = cfg.grid.get("seeds_of") or {}
    if listed != [str(n)] or seeds_of:
        print(f"seed={n}: running seed {n} (instead of the experiment's grid.seeds [{', '.join(listed)}]"
              + (f" and grid.seeds_of {OmegaConf.to_container(seeds_of)}" if seeds_of else "") + ")", flush=True)
    return [n]


def grid_datasets(cfg: DictConfig, overrides: list[str]) -> tuple[list[str], list[str] | None]:
    """The grid's datasets and scene filter. ``dataset=Y`` on the command line runs the experiment's
    grid (methods, budgets, seeds) on Y alone, with Y's own scenes (a folder given by dataset.path is
    its one scene), unless ``grid.datasets=`` / ``grid.scenes=`` are given too."""
    grid = cfg.grid
    datasets = [str(d) for d in grid.datasets]
    scenes = None if grid.scenes is None else [str(s) for s in grid.scenes]
    chosen = _given(overrides, "dataset")
    if chosen is not None:
        if _given(overrides, "grid.datasets") is None:
            datasets = [chosen]
        if _given(overrides, "grid.scenes") is None:
            scenes = None
    return datasets, scenes


def check_command_line(args: list[str]) -> str | None:
    """A command-line mistake Hydra would only answer with its own words: what is wrong and the fix."""
    if _given(args, "dataset.path") is not None and _given(args, "dataset") is None \
            and _given(args, "grid.datasets") is None:
        return ("dataset.path names a scene folder of the dataset kinds that take one: add dataset=colmap "
                "(images/ and sparse/0/) or dataset=transforms (transforms.json) before it")
    dataset = _given(args, "dataset")
    if dataset is not None and not has_config("dataset", dataset):
        return unknown_dataset(dataset)
    method = _given(args, "method")
    if method is not None and not has_config("method", method):
        return unknown_method(method, "method")
    return None


def unknown_method(name: str, key: str) -> str:
    """The one-block message for a method name (given as ``key``) that no config file or registry
    knows, listing the known ones; a registered plugin method without a file runs through the grid."""
    from baselines.registry import list_methods

    known = list_methods()
    if name in known:
        return f"{key}={name} is a plugin method without a file in configs/method/: run it with grid.methods=[{name}]"
    return f"{key}={name} is no method; known methods: {', '.join(known)}"


def unknown_dataset(name: str) -> str:
    """The one-block message for ``dataset=NAME`` without a file in configs/dataset/: a registered
    plugin scene format or dataset runs through the grid; another name lists the known ones."""
    from smgs.data.registry import list_names

    if name in list_names():
        return (f"dataset={name} is a plugin scene format or dataset without a file in configs/dataset/: run it "
                f"with grid.datasets=[{name}] (its settings as +dataset.KEY=VALUE)")
    files = sorted(p.stem for p in (Path(CONFIG_DIR) / "dataset").glob("*.yaml") if p.stem != "plugin")
    return f"dataset={name} is no dataset; known: {', '.join(files)} (and the scene formats {', '.join(list_names())})"


def plan(cfg: DictConfig, overrides: list[str]) -> tuple[list[Cell], list[dict]]:
    """The grid's cells and their payloads (resolved configs, run directories and the method's
    settings made from each config once: ``protocols.run_settings.cell_settings``). A grid that
    cannot run (an unknown method or scene, an empty list, a bad seed count or folder name) stops
    here in the one-block form, before anything runs."""
    from protocols.run_settings import cell_settings

    try:
        cells = grid_cells(cfg, overrides)
        check_path_names(str(cfg.experiment_name), cells)
    except ValueError as e:
        raise SystemExit(f"invalid config, nothing was run: {e}") from None
    out = Path(cfg.out_dir)
    payloads = []
    for c in cells:
        try:
            ccfg = _cell_config(c, overrides)
        except ValueError as e:   # ours (a budget with no file); Hydra's own errors keep their words
            raise SystemExit(f"invalid config, nothing was run: {e}") from None
        payloads.append({"key": c.key, "run_dir": str(out / c.key), "config": ccfg, "settings": cell_settings(ccfg)})
    return cells, payloads


def grid_cells(cfg: DictConfig, overrides: list[str]) -> list[Cell]:
    """The grid's cells; a ValueError names the key that makes them impossible."""
    from baselines.registry import get_spec

    grid = cfg.grid
    for key in ("methods", "datasets", "budgets"):
        if not grid[key]:
            raise ValueError(f"grid.{key} is empty: the experiment would run nothing; list at least one")
    for m in grid.methods:
        try:
            get_spec(str(m))
        except KeyError:
            raise ValueError(unknown_method(str(m), "grid.methods")) from None
    names, scenes = grid_datasets(cfg, overrides)
    datasets = {d: _scenes_of(d, overrides) for d in names}
    seeds, seeds_of = grid_seeds(cfg, overrides)
    unseeded = [str(m) for m in grid.methods if not seeds_of.get(str(m), seeds)]
    if unseeded:
        raise ValueError(f"no seed to run for {', '.join(unseeded)}: grid.seeds is empty; list at least one "
                         "(grid.seeds=[0]) or give seeds=N")
    return expand([str(m) for m in grid.methods], datasets, [str(b) for b in grid.budgets], seeds, scenes, seeds_of)


def grid_seeds(cfg: DictConfig, overrides: list[str] = ()) -> tuple[list[int], dict[str, list[int]]]:
    """The grid's seeds and per-method exceptions: ``seed=N`` on the command line runs seed N
    (``_seed_given``, docs/runs.md); ``seeds=N`` runs seeds 0 … N−1 of every method; otherwise
    ``grid.seeds``, with ``grid.seeds_of`` (method -> seeds) for the methods it names
    (docs/reports.md, "Running N seeds")."""
    one = _seed_given(cfg, list(overrides))
    if one is not None:
        return one, {}
    n = cfg.get("seeds")
    if n is not None:
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(f"seeds={n!r}: give the number of seeds, a whole number ≥ 1 (seeds=3 runs seeds 0, 1, "
                             "2; for a list of seed numbers use grid.seeds=[...])")
        return list(range(n)), {}
    seeds_of = cfg.grid.get("seeds_of") or {}
    return ([int(s) for s in cfg.grid.seeds],
            {str(m): [int(s) for s in v] for m, v in OmegaConf.to_container(seeds_of).items()} if seeds_of else {})


def _preflight(payloads: list[dict]) -> None:
    """Every cell's scene before anything runs, each scene once: missing data stops the experiment
    under on_missing=error; a scene that is there but cannot give a meaningful result (a folder that
    is no scene, broken intrinsics or poses, an image listed twice, images too small) stops it
    whatever on_missing says, naming the file and the fix."""
    from protocols.cell_scene import check_available, scene_problem

    missing: dict[str, str] = {}
    broken: list[str] = []
    seen: set[str] = set()
    for p in payloads:
        c = p["config"]
        key = json.dumps([c["dataset"], c.get("scene"), c.get("protocol"), c.get("data_root")], sort_keys=True,
                         default=str)
        if key in seen:
            continue
        seen.add(key)
        err = check_available(c)
        if err:
            if c.get("on_missing", "error") == "error":
                missing[key] = err
            continue
        problem = scene_problem(c)
        if problem and problem not in broken:
            broken.append(problem)
    if broken:
        raise SystemExit("invalid scene, nothing was run:\n  " + "\n  ".join(broken))
    if missing:
        raise SystemExit(missing_data_message(list(dict.fromkeys(missing.values())), len(missing) == len(seen)))


def missing_data_message(problems: list[str], all_missing: bool) -> str:
    """The message of an experiment stopped by missing data: where each was looked for, and what to
    do, which is not on_missing=skip when no scene of the experiment is there (it would run nothing)."""
    if all_missing:
        advice = ("no scene of the experiment is there: put the data where the lines below say, or point at it "
                  "with data_root=PATH (or dataset.path=PATH for your own scene)")
    else:
        advice = "set on_missing=skip to run the scenes that are there"
    return f"missing data, nothing was run ({advice}):\n  " + "\n  ".join(problems)


REMOTE_EXECUTORS = ("slurm",)


def check_devices(payloads: list[dict], executor: str) -> None:
    """Every cell's device and renderer backend, before anything runs or is written: a device this
    machine cannot provide (``device=cuda`` without CUDA, ``cuda:3`` with fewer GPUs), an unknown
    name, or a backend bound to the other kind of device stops the experiment with the fix. Cells
    that run on other machines (SLURM) are checked for spelling and backend here and for the
    hardware on their node."""
    from smgs.device import DeviceError, parse_device, resolve_device
    from smgs.raster.backends import check_backend

    problems = []
    for p in payloads:
        c = p["config"]
        try:
            dev = parse_device(c.get("device")) if executor in REMOTE_EXECUTORS else resolve_device(c.get("device"))
            if dev is not None:
                check_backend(str(c.get("backend", "auto")), dev)
        except DeviceError as e:
            if str(e) not in problems:
                problems.append(str(e))
    if problems:
        raise SystemExit("device: " + "\n  ".join(problems))


def _run(cfg: DictConfig, overrides: list[str]) -> list[dict]:
    from protocols.cell import run_cell
    from protocols.executors import execute
    from protocols.progress import cell_status

    from protocols.validate import schedule_warning, validate_payloads

    problem = out_dir_problem(Path(cfg.out_dir))
    if problem:
        raise SystemExit(f"nothing was run: {problem}")
    cells, payloads = plan(cfg, overrides)
    if cfg.report:
        from protocols.report_step import builder

        try:
            builder(cfg.get("report_builder"))   # a report_builder that names no function stops here
        except ValueError as e:
            raise SystemExit(f"invalid config, nothing was run: {e}") from None
    check_devices(payloads, str(cfg.executor.kind))
    validate_payloads(payloads)
    _preflight(payloads)
    for warning in dict.fromkeys(w for w in (schedule_warning(p["config"], p["settings"]) for p in payloads) if w):
        print(f"warning: {warning}", flush=True)
    ex = cfg.executor
    print(f"experiment {cfg.experiment_name}: {len(cells)} run(s) -> {cfg.out_dir}", flush=True)
    summaries = execute(run_cell, payloads, kind=str(ex.kind), workers=int(ex.workers),
                        slurm=OmegaConf.to_container(ex.slurm, resolve=True), folder=str(ex.slurm.folder))
    counts: dict[str, int] = {}
    for s in summaries:
        k = cell_status(s)
        counts[k] = counts.get(k, 0) + 1
        if s["status"] != "ok":
            where = f" (traceback in {s['log']})" if s.get("log") else ""
            print(f"  {s['key']}: {s['status']}: {s.get('error')}{where}", flush=True)
    print("runs: " + ", ".join(f"{v} {k}" for k, v in sorted(counts.items())), flush=True)
    if cfg.report:
        from protocols.report_step import build_report

        path = build_report(Path(cfg.out_dir), cfg.get("report_builder"))
        print(f"report: {path}", flush=True)
    return summaries


def run_experiment(overrides: list[str]) -> list[dict]:
    """Run an experiment from Hydra overrides (e.g. ["+experiment=smoke", "protocol.steps=50"])
    without the command line: for tests and notebooks."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return _run(compose(config_name="config", overrides=overrides), list(overrides))


def failure_message(summaries: list[dict]) -> str | None:
    """What the exit status stands for: None when no cell failed."""
    failed = sum(s["status"] == "failed" for s in summaries)
    return f"{failed} of {len(summaries)} run(s) failed (their errors are listed above)" if failed else None


@hydra.main(config_path=CONFIG_DIR, config_name="config", version_base="1.3")  # absolute: also when imported by the smgs command
def main(cfg: DictConfig) -> None:
    from protocols.report_step import ReportFailed

    try:
        summaries = _run(cfg, list(HydraConfig.get().overrides.task))
    except ReportFailed as e:   # the runs are recorded; the builder's error is in the message
        print(f"error: {e}", file=sys.stderr, flush=True)
        raise SystemExit(1) from None
    message = failure_message(summaries)
    if message:  # a script or CI job driving the harness must see it
        print(f"error: {message}", file=sys.stderr, flush=True)
        raise SystemExit(1)


def cli() -> None:
    # `--force` is accepted as a flag as well as the Hydra override force=true
    if "--force" in sys.argv:
        sys.argv = [a for a in sys.argv if a != "--force"] + ["force=true"]
    name = _given(sys.argv[1:], "experiment_name")   # before Hydra makes ${out_dir}/_hydra from it
    problem = path_name_problem("experiment_name", name) if name is not None else None
    if problem:
        print(f"error: {problem} (it names the folder below the output root; set out_dir=PATH to write "
              "elsewhere)", file=sys.stderr, flush=True)
        raise SystemExit(2)
    problem = check_command_line(sys.argv[1:])
    if problem:
        print(f"error: invalid config, nothing was run: {problem}", file=sys.stderr, flush=True)
        raise SystemExit(2)
    out = composed_out_dir(CONFIG_DIR, sys.argv[1:])   # before Hydra writes its log there
    problem = out_dir_problem(out) if out is not None else None
    if problem:
        print(f"error: nothing was run: {problem}", file=sys.stderr, flush=True)
        raise SystemExit(2)
    signal.signal(signal.SIGTERM, on_sigterm)
    try:
        main()
    except Terminated:
        print("\nstopped by SIGTERM: the running cell was interrupted cleanly; rerun the same command to "
              "resume from its last checkpoint", file=sys.stderr, flush=True)
        raise SystemExit(128 + signal.SIGTERM) from None


if __name__ == "__main__":
    cli()
