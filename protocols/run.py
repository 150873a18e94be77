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
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from protocols.cell_stop import Terminated
from protocols.executors import on_sigterm
from protocols.config_files import CONFIG_DIR, config_names, has_config
from protocols.grid import Cell, check_path_names, expand, path_name_problem
from protocols.grid_axes import given as _given, grid_datasets, grid_seeds, one_or_list
from protocols.method_defaults import register as register_method_defaults
from protocols.out_dir import out_dir_problem
from protocols.refused import EXIT_REFUSED, Refused

log = logging.getLogger("smgs.protocols")


register_method_defaults()   # the built-in methods' configs take the trainer's defaults from the code (Hydra's store)
GRID_KEYS = ("method=", "dataset=", "budget=", "seed=", "seeds=", "scene=", "method.name=")


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
    raise ValueError(f"budget {budget!r} (grid.budgets) is no file in configs/budget/ ({', '.join(config_names('budget'))}); "
                     f"to make one, start from a file and name it: budget=cap4 budget.cap=N budget.name={budget}")


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
    files = [n for n in config_names("dataset") if n != "plugin"]
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
        raise Refused(f"invalid config, nothing was run: {e}") from None
    out = Path(cfg.out_dir)
    payloads = []
    for c in cells:
        try:
            ccfg = _cell_config(c, overrides)
        except ValueError as e:   # ours (a budget with no file); Hydra's own errors keep their words
            raise Refused(f"invalid config, nothing was run: {e}") from None
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
    methods = one_or_list(cfg, overrides, "methods", "method", str(cfg.method.name))
    budgets = one_or_list(cfg, overrides, "budgets", "budget", str(cfg.budget.name))
    names, scenes = grid_datasets(cfg, overrides)
    datasets = {d: _scenes_of(d, overrides) for d in names}
    seeds, seeds_of = grid_seeds(cfg, overrides)
    unseeded = [m for m in methods if not seeds_of.get(m, seeds)]
    if unseeded:
        raise ValueError(f"no seed to run for {', '.join(unseeded)}: grid.seeds is empty; list at least one "
                         "(grid.seeds=[0]) or give seeds=N")
    return expand(methods, datasets, budgets, seeds, scenes, seeds_of)


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
        raise Refused("invalid scene, nothing was run:\n  " + "\n  ".join(broken))
    if missing:
        raise Refused(missing_data_message(list(dict.fromkeys(missing.values())), len(missing) == len(seen)))


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
        raise Refused("device: " + "\n  ".join(problems))


@dataclass(frozen=True)
class Prepared:
    """An experiment checked and ready to run: its config, cells and their payloads."""

    cfg: DictConfig
    cells: list[Cell]
    payloads: list[dict]


def prepare(cfg: DictConfig, overrides: list[str]) -> Prepared:
    """The grid planned and every check done (its out_dir, settings, devices, scenes and data),
    before anything runs or is written (``cli`` calls it before Hydra writes its log in out_dir); a
    ``Refused`` names what stops it."""
    from protocols.validate import validate_payloads

    problem = out_dir_problem(Path(str(cfg.out_dir)))
    if problem:
        raise Refused(f"nothing was run: {problem}")
    cells, payloads = plan(cfg, overrides)
    if cfg.report:
        from protocols.report_step import builder

        try:
            builder(cfg.get("report_builder"))   # a report_builder that names no function stops here
        except ValueError as e:
            raise Refused(f"invalid config, nothing was run: {e}") from None
    check_devices(payloads, str(cfg.executor.kind))
    if str(cfg.executor.kind) == "slurm":   # its settings and commands (sbatch's own word comes at submission)
        from protocols.slurm_sweep import checked_settings

        checked_settings(OmegaConf.to_container(cfg.executor.slurm, resolve=True))
    validate_payloads(payloads)
    _preflight(payloads)
    return Prepared(cfg, cells, payloads)


def run_prepared(prepared: Prepared) -> list[dict]:
    """Run the prepared cells with the chosen executor, then build the report."""
    from protocols.cell import run_cell
    from protocols.executors import execute
    from protocols.progress import cell_status

    from protocols.validate import schedule_warning

    cfg, cells, payloads = prepared.cfg, prepared.cells, prepared.payloads
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
        elif s.get("rerun"):   # a finished cell run again: why (another config, changed inputs, --force)
            print(f"  {s['key']}: rerun: {s['rerun']}", flush=True)
    print("runs: " + ", ".join(f"{v} {k}" for k, v in sorted(counts.items())), flush=True)
    if cfg.report:
        from protocols.report_step import build_report

        path = build_report(Path(cfg.out_dir), cfg.get("report_builder"))
        print(f"report: {path}", flush=True)
    return summaries


def _run(cfg: DictConfig, overrides: list[str]) -> list[dict]:
    return run_prepared(prepare(cfg, overrides))


def compose_checked(overrides: list[str]) -> DictConfig:
    """The config of ``overrides`` (Hydra initialised), after refusing every key that nothing would
    read (``protocols.known_keys``); Hydra's own refusals come as ``Refused`` too."""
    from hydra import compose
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from protocols.known_keys import group_choices, unread_keys

    try:
        base = compose(config_name="config", overrides=group_choices(overrides))
        problems = unread_keys(OmegaConf.to_container(base, resolve=False), overrides)
        if problems:
            raise Refused("invalid config, nothing was run:\n  " + "\n  ".join(problems))
        return compose(config_name="config", overrides=overrides)
    except (HydraException, OmegaConfBaseException) as e:
        words = " ".join(str(e).split("Config search path")[0].split())
        raise Refused(f"invalid config, nothing was run: {words}") from None


def run_experiment(overrides: list[str]) -> list[dict]:
    """Run an experiment from Hydra overrides (e.g. ["+experiment=smoke", "protocol.steps=50"])
    without the command line: for tests and notebooks."""
    from hydra import initialize_config_dir

    overrides = list(overrides)
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return _run(compose_checked(overrides), overrides)


def failure_message(summaries: list[dict]) -> str | None:
    """What the exit status stands for: None when no cell failed."""
    failed = sum(s["status"] == "failed" for s in summaries)
    return f"{failed} of {len(summaries)} run(s) failed (their errors are listed above)" if failed else None


def _finish(summaries_of: Callable[[], list[dict]]) -> None:
    """Run, and stop with status 1 where a run or the report failed (a script or CI job driving the
    harness must see it)."""
    from protocols.report_step import ReportFailed

    try:
        summaries = summaries_of()
    except ReportFailed as e:   # the runs are recorded; the builder's error is in the message
        print(f"error: {e}", file=sys.stderr, flush=True)
        raise SystemExit(1) from None
    message = failure_message(summaries)
    if message:
        print(f"error: {message}", file=sys.stderr, flush=True)
        raise SystemExit(1)


@hydra.main(config_path=CONFIG_DIR, config_name="config", version_base="1.3")  # absolute: also when imported by the smgs command
def main(cfg: DictConfig) -> None:
    """The whole run under Hydra's own command line (what ``cli`` hands Hydra's flags to)."""
    overrides = list(HydraConfig.get().overrides.task)
    _finish(lambda: _run(cfg, overrides))


def _under_hydra(args: list[str], task: Callable[[], None] | None) -> None:
    """Hydra's main with ``args`` as its command line: its logging (stdout and <out_dir>/_hydra/run.log)
    around ``task``, or, for ``task`` None, the whole run (``main``)."""
    saved = sys.argv
    sys.argv = ["smgs run", *args]
    try:
        if task is None:
            main()
        else:
            hydra.main(config_path=CONFIG_DIR, config_name="config", version_base="1.3")(lambda _cfg: task())()
    finally:
        sys.argv = saved


def _refusal(args: list[str]) -> str | None:
    """What stops the command line before Hydra sees it (a setting written as a flag, a folder name
    that cannot be one, a dataset or method that is not there)."""
    from protocols.run_help import flag_problem

    problem = flag_problem(args)
    if problem:
        return problem
    name = _given(args, "experiment_name")   # before Hydra makes ${out_dir}/_hydra from it
    problem = path_name_problem("experiment_name", name) if name is not None else None
    if problem:
        return f"{problem} (it names the folder below the output root; set out_dir=PATH to write elsewhere)"
    problem = check_command_line(args)
    return f"invalid config, nothing was run: {problem}" if problem else None


def cli(argv: list[str] | None = None) -> int:
    """``smgs run`` / ``python -m protocols.run``: every check before anything is written (also
    Hydra's <out_dir>/_hydra/run.log), then the run under Hydra's logging. A refusal prints one
    block and exits with status 2, a failed run with 1."""
    from protocols.run_help import hydra_flags, run_help

    args = list(sys.argv[1:] if argv is None else argv)
    if "-h" in args or "--help" in args:
        print(run_help())
        return 0
    # `--force` is accepted as a flag as well as the Hydra override force=true
    if "--force" in args:
        args = [a for a in args if a != "--force"] + ["force=true"]
    signal.signal(signal.SIGTERM, on_sigterm)
    try:
        problem = _refusal(args)
        if problem:
            raise Refused(problem)
        if hydra_flags(args):
            _under_hydra(args, None)
            return 0
        from hydra import initialize_config_dir

        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
            prepared = prepare(compose_checked(args), args)   # before Hydra writes its log in out_dir
        _under_hydra(args, lambda: _finish(lambda: run_prepared(prepared)))
    except Refused as e:
        print(f"error: {e.message}", file=sys.stderr, flush=True)
        raise SystemExit(EXIT_REFUSED) from None
    except Terminated:
        print("\nstopped by SIGTERM: the running cell was interrupted cleanly; rerun the same command to "
              "resume from its last checkpoint", file=sys.stderr, flush=True)
        raise SystemExit(128 + signal.SIGTERM) from None
    return 0


if __name__ == "__main__":
    sys.exit(cli())
