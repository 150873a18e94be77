"""The grid's axes (methods, datasets and scenes, budgets, seeds) as the command line leaves them.

An experiment lists its axes under ``grid``; the command line may name one value of an axis
(``method=``, ``dataset=``, ``scene=``, ``budget=``, ``seed=``, ``seeds=N``) or the list itself
(``grid.methods=``, ...). One rule for all: what the command line gives wins over what the
experiment lists, and the plan says so where it replaces the experiment's value; a single value and
a list of the same axis both given and disagreeing stop the sweep naming both. Nothing given on the
command line is silently outvoted (``grid.seeds=[0]`` under an experiment's ``grid.seeds_of``
once ran three seeds without a word).
"""

from __future__ import annotations

from collections.abc import Iterator

from omegaconf import DictConfig, OmegaConf


def _settings(overrides: list[str]) -> Iterator[tuple[str, str, str]]:
    """Each ``key=V`` of the command line (also ``+key=V``, ``++key=V``) as (key, V, the override
    without its ``+``)."""
    for o in overrides:
        text = o.lstrip("+")
        k, sep, v = text.partition("=")
        if sep:
            yield k, v, text


def given(overrides: list[str], key: str) -> str | None:
    """The value the command line gives ``key`` (``key=V``, ``+key=V`` or ``++key=V``; the last)."""
    return next((v for k, v, _ in reversed(list(_settings(overrides))) if k == key), None)


def touched(overrides: list[str], key: str) -> str | None:
    """The command line's setting of ``key`` or of a key below it, as written without its ``+``
    (``grid.seeds_of.slow=[0,1]`` sets ``grid.seeds_of``); None where it sets neither."""
    return next((t for k, _, t in _settings(overrides) if k == key or k.startswith(key + ".")), None)


def _say(text: str) -> None:
    print(text, flush=True)


def _listed(values) -> str:
    return ", ".join(str(v) for v in values)


def one_or_list(cfg: DictConfig, overrides: list[str], axis: str, single: str, value: str) -> list[str]:
    """The grid's ``axis`` (``methods``, ``budgets``): ``single=X`` on the command line (its resolved
    name ``value``) runs X alone instead of the experiment's list, unless ``grid.<axis>`` is given
    too, which must then be [X]."""
    listed = [str(x) for x in cfg.grid[axis]]
    if given(overrides, single) is None:
        return listed
    if given(overrides, f"grid.{axis}") is not None:
        if listed != [value]:
            raise ValueError(f"{single}={given(overrides, single)} and grid.{axis}=[{_listed(listed)}] disagree; give "
                             f"{single}=NAME to run one, or grid.{axis}=[...] to run several")
        return listed
    if listed != [value]:
        _say(f"{single}={given(overrides, single)}: running {value} (instead of the experiment's grid.{axis} "
             f"[{_listed(listed)}])")
    return [value]


def grid_datasets(cfg: DictConfig, overrides: list[str]) -> tuple[list[str], list[str] | None]:
    """The grid's datasets and scene filter. ``dataset=Y`` on the command line runs the experiment's
    grid (methods, budgets, seeds) on Y alone, with Y's own scenes (a folder given by dataset.path is
    its one scene), unless ``grid.datasets=`` / ``grid.scenes=`` are given too; ``scene=S`` runs S
    alone of them, unless ``grid.scenes=`` is given too."""
    grid = cfg.grid
    datasets = [str(d) for d in grid.datasets]
    scenes = None if grid.scenes is None else [str(s) for s in grid.scenes]
    chosen = given(overrides, "dataset")
    if chosen is not None:
        if given(overrides, "grid.datasets") is None:
            datasets = [chosen]
        if given(overrides, "grid.scenes") is None:
            scenes = None
    scene = given(overrides, "scene")
    if scene is not None and scene != "null":
        if given(overrides, "grid.scenes") is not None and scenes != [scene]:
            raise ValueError(f"scene={scene} and grid.scenes=[{_listed(scenes or [])}] disagree; give scene=NAME to "
                             "run one, or grid.scenes=[...] to run several")
        scenes = [scene]
    return datasets, scenes


def seed_given(cfg: DictConfig, overrides: list[str]) -> list[int] | None:
    """``seed=N`` on the command line: [N], also under an experiment whose ``grid.seeds`` (or
    ``grid.seeds_of``) lists other seeds, which it replaces (and says so); None when not given.
    Given with ``seeds=M`` or with a ``grid.seeds`` that is not [N], the sweep stops naming both."""
    text = given(overrides, "seed")
    if text is None:
        return None
    try:
        n = int(text)
    except ValueError:
        raise ValueError(f"seed={text!r} is not an integer") from None
    if cfg.get("seeds") is not None:
        raise ValueError(f"seed={text} and seeds={cfg.get('seeds')} disagree; give seed=N to run one seed, or seeds=M "
                         "to run seeds 0 … M-1")
    listed = [str(x) for x in cfg.grid.seeds]
    if given(overrides, "grid.seeds") is not None and listed != [str(n)]:
        raise ValueError(f"seed={text} and grid.seeds=[{', '.join(listed)}] disagree; give seed=N to run one seed, "
                         "or grid.seeds=[...] to run several")
    seeds_of = cfg.grid.get("seeds_of") or {}
    if listed != [str(n)] or seeds_of:
        _say(f"seed={n}: running seed {n} (instead of the experiment's grid.seeds [{', '.join(listed)}]"
             + (f" and grid.seeds_of {OmegaConf.to_container(seeds_of)}" if seeds_of else "") + ")")
    return [n]


def _seed_count(cfg: DictConfig, overrides: list[str]) -> list[int]:
    """``seeds=N``: seeds 0 … N−1 of every method, replacing the experiment's ``grid.seeds`` and
    ``grid.seeds_of`` (and saying so); given with either of them on the command line, it stops."""
    n = cfg.get("seeds")
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"seeds={n!r}: give the number of seeds, a whole number ≥ 1 (seeds=3 runs seeds 0, 1, "
                         "2; for a list of seed numbers use grid.seeds=[...])")
    for key in ("grid.seeds", "grid.seeds_of"):
        if touched(overrides, key) is not None:
            raise ValueError(f"seeds={n} and {touched(overrides, key)} disagree; give seeds=N to run seeds 0 … "
                             f"N-1 of every method, or {key} alone")
    seeds = list(range(n))
    listed = [int(s) for s in cfg.grid.seeds]
    seeds_of = cfg.grid.get("seeds_of") or {}
    if seeds_of or listed != seeds:
        _say(f"seeds={n}: running seeds {_listed(seeds)} of every method (instead of the experiment's grid.seeds "
             f"[{_listed(listed)}]" + (f" and grid.seeds_of {OmegaConf.to_container(seeds_of)}" if seeds_of else "")
             + ")")
    return seeds


def grid_seeds(cfg: DictConfig, overrides: list[str] = ()) -> tuple[list[int], dict[str, list[int]]]:
    """The grid's seeds and per-method exceptions: ``seed=N`` on the command line runs seed N
    (``seed_given``, docs/runs.md); ``seeds=N`` runs seeds 0 … N−1 of every method; otherwise
    ``grid.seeds``, with ``grid.seeds_of`` (method -> seeds) for the methods it names
    (docs/reports.md, "Running N seeds"). ``grid.seeds`` given on the command line replaces the
    experiment's ``grid.seeds_of`` too (saying so), unless ``grid.seeds_of`` is given as well."""
    overrides = list(overrides)
    one = seed_given(cfg, overrides)
    if one is not None:
        return one, {}
    if cfg.get("seeds") is not None:
        return _seed_count(cfg, overrides), {}
    seeds = [int(s) for s in cfg.grid.seeds]
    listed_of = cfg.grid.get("seeds_of")
    seeds_of = {str(m): [int(s) for s in v] for m, v in OmegaConf.to_container(listed_of).items()} if listed_of else {}
    if seeds_of and given(overrides, "grid.seeds") is not None:
        if touched(overrides, "grid.seeds_of") is None:
            _say(f"grid.seeds=[{_listed(seeds)}]: every method runs seeds {_listed(seeds)} (instead of the experiment's "
                 f"grid.seeds_of {seeds_of})")
            return seeds, {}
        _say(f"grid.seeds=[{_listed(seeds)}] and grid.seeds_of {seeds_of}: {', '.join(seeds_of)} run their "
             "grid.seeds_of seeds, the other methods grid.seeds")
    return seeds, seeds_of
