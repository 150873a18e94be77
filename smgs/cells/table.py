"""Results as data: the cells of one or more results trees as tidy pandas tables.

``cells``: one row per cell (failed and skipped cells too, with their reason); ``views``: one row per
cell and test view; ``curve_points``: the error-against-time curves, one row per evaluation. Columns
and dtypes are fixed (``CELL_COLUMNS``, ``VIEW_COLUMNS``, ``CURVE_COLUMNS``; docs/reports.md lists
them): a value a cell did not record is missing (NaN / <NA>), never a zero. The reports are computed
from ``cells`` (reports/aggregate.py). pandas is imported here only, so ``import smgs`` stays cheap.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable

from smgs.atomic import atomic_write_bytes
from smgs.cells.result import RunResult
from smgs.cells.tree import LoadedRuns, is_pattern, load_runs, pattern_cap

if TYPE_CHECKING:
    import pandas as pd

METRICS = ("psnr", "ssim", "lpips", "flip")
CONSISTENCY = ("psnr", "mse", "flip", "pop_ratio", "popped_fraction")
NOT_RECORDED = "not recorded"

# what names a cell (the experiment that ran it beside: a runs folder may hold several sweeps)
KEY_COLUMNS: dict[str, str] = {"method": "string", "dataset": "string", "scene": "string", "budget": "string",
                            "cap": "Int64", "preset": "string", "seed": "int64", "experiment": "string"}
CELL_COLUMNS: dict[str, str] = {
    **KEY_COLUMNS, "status": "string", "reason": "string",
    **{m: "float64" for m in METRICS}, **{f"{m}_missing": "string" for m in METRICS}, "lpips_net": "string",
    "num_gaussians": "Int64", "train_seconds": "float64", "build_seconds": "float64", "render_fps": "float64",
    "peak_memory_mb": "float64", "steps": "Int64",
    **{f"consistency_{k}": "float64" for k in CONSISTENCY},
    **{f"consistency_{k}_missing": "string" for k in CONSISTENCY},
    "consistency_flip_name": "string", "consistency_flow": "string", "consistency_mask": "string",
    "frac_within_kmax": "float64", "collapsed": "boolean",
    "device": "string", "render_device": "string", "backend": "string", "renderer": "string", "threads": "Int64",
    "config_hash": "string", "inputs_fingerprint": "string", "source": "string", "git": "string", "path": "string",
}
VIEW_COLUMNS: dict[str, str] = {**KEY_COLUMNS, "status": "string", "reason": "string", "view": "string",
                                "view_index": "Int64", **{m: "float64" for m in METRICS}, "path": "string"}
CURVE_COLUMNS: dict[str, str] = {**KEY_COLUMNS, "step": "int64", "seconds": "float64", "psnr": "float64",
                                 "num_gaussians": "Int64", "path": "string"}


def results(*runs_dirs: Path | str, per_view: bool = False) -> "pd.DataFrame":
    """Every cell below the runs directories (one row each; ``per_view``: one row per cell and test
    view). Files that could not be read are left out with a warning and listed in
    ``df.attrs["unreadable"]``; copies of a cell in ``df.attrs["duplicates"]`` (the kept one is the
    row)."""
    loaded = read(runs_dirs)
    df = views(loaded) if per_view else cells(loaded)
    return _with_attrs(df, loaded)


def curves(*runs_dirs: Path | str) -> "pd.DataFrame":
    """The error against train time of every cell below the runs directories: one row per evaluation
    during training (cells that recorded no curve, e.g. failed ones, have no row)."""
    loaded = read(runs_dirs)
    return _with_attrs(curve_points(loaded), loaded)


def read(runs_dirs: Iterable[Path | str | Iterable[Path | str]]) -> LoadedRuns:
    """The runs below the directories (given one by one, or as a list)."""
    dirs = [Path(d) for x in runs_dirs for d in ([x] if isinstance(x, (str, Path)) else x)]
    if not dirs:
        raise TypeError("smgs.results needs at least one runs directory, e.g. smgs.results('runs/my_sweep')")
    for d in dirs:
        if not d.is_dir():
            raise FileNotFoundError(f"{d} is not a directory: smgs.results reads every results.json below the runs "
                                    "directories it is given (a sweep's out_dir); check the path")
    loaded = load_runs(*dirs)
    for path, why in loaded.unreadable:
        warnings.warn(f"left out, unreadable: {path}: {why}", stacklevel=3)
    return loaded


def _with_attrs(df: "pd.DataFrame", loaded: LoadedRuns) -> "pd.DataFrame":
    df.attrs["unreadable"] = [(str(p), why) for p, why in loaded.unreadable]
    df.attrs["duplicates"] = [(str(a), str(b)) for a, b in loaded.duplicates]
    return df


def cells(loaded: LoadedRuns) -> "pd.DataFrame":
    """One row per loaded run, in ``loaded.runs`` order (row i is ``loaded.runs[i]``)."""
    return frame([cell_record(run.result, run.path) for run in loaded.runs], CELL_COLUMNS)


def views(loaded: LoadedRuns) -> "pd.DataFrame":
    recs = []
    for run in loaded.runs:
        r = run.result
        base = {**_identity(r), "status": r.status, "reason": _reason(r), "path": str(run.path)}
        pv = r.per_view or {}
        n = max((len(v) for v in pv.values() if isinstance(v, list)), default=0)
        if n == 0:   # no per-view values (a failed cell, an older run): the cell is still a row
            recs.append(base)
        names = pv.get("name") if isinstance(pv.get("name"), list) else []
        for i in range(n):
            recs.append({**base, "view": names[i] if i < len(names) else None, "view_index": i,
                         **{m: _at(pv.get(m), i) for m in METRICS}})
    return frame(recs, VIEW_COLUMNS)


def curve_points(loaded: LoadedRuns) -> "pd.DataFrame":
    recs = [{**_identity(run.result), "step": c.step, "seconds": _number(c.seconds), "psnr": _number(c.psnr),
             "num_gaussians": c.num_gaussians, "path": str(run.path)}
            for run in loaded.runs for c in run.result.curve]
    return frame(recs, CURVE_COLUMNS)


def frame(records: list[dict], columns: dict[str, str]) -> "pd.DataFrame":
    import pandas as pd

    df = pd.DataFrame.from_records(records, columns=list(columns))
    return df.astype(columns) if len(df) else pd.DataFrame({c: pd.Series(dtype=t) for c, t in columns.items()})


# ---- writing a table ------------------------------------------------------------------------------

FORMATS = ("csv", "parquet", "json")
PARQUET_HELP = ("parquet needs pyarrow (or fastparquet), which smgs does not install (pyarrow is a 55 MB wheel "
                "that nothing else here needs): pip install pyarrow, or pip install 'smgs[parquet]'; or write "
                "--format csv or json")


class ParquetUnavailable(ImportError):
    """Parquet asked for where pandas finds no parquet engine."""


def encode(df: "pd.DataFrame", fmt: str) -> bytes:
    """``df`` as a file of ``fmt``: csv (missing values empty), json (a list of records, missing values
    null) or parquet (the dtypes kept)."""
    if fmt == "csv":
        return df.to_csv(index=False).encode()
    if fmt == "json":
        return df.to_json(orient="records", indent=1).encode()
    if fmt == "parquet":
        buf = io.BytesIO()
        try:
            df.to_parquet(buf, index=False)
        except ImportError as e:
            raise ParquetUnavailable(PARQUET_HELP) from e
        return buf.getvalue()
    raise ValueError(f"unknown format {fmt!r}: one of {', '.join(FORMATS)}")


def format_for(path: Path | str | None) -> str:
    """The format a file's suffix names (.csv, .parquet, .json), else csv (also for no file: stdout)."""
    suffix = Path(path).suffix[1:].lower() if path is not None else ""
    return suffix if suffix in FORMATS else "csv"


def write(df: "pd.DataFrame", path: Path | str, fmt: str | None = None) -> Path:
    """Write ``df`` to ``path`` whole or not at all (``smgs.atomic``); ``fmt`` defaults to the suffix of
    ``path`` (``format_for``)."""
    path = Path(path)
    atomic_write_bytes(path, encode(df, fmt or format_for(path)))
    return path


# ---- one cell ---------------------------------------------------------------------------------------

def cell_record(r: RunResult, path: Path | str) -> dict[str, Any]:
    ok = r.status == "ok"
    rec: dict[str, Any] = {**_identity(r), "status": r.status, "reason": _reason(r)}
    for m in METRICS:
        rec[m], why = _metric(r, m)
        rec[f"{m}_missing"] = why if ok else None
    rec["lpips_net"] = r.lpips_net
    for f in ("num_gaussians", "steps"):
        rec[f] = _integer(getattr(r, f))
    for f in ("train_seconds", "build_seconds", "render_fps", "peak_memory_mb"):
        rec[f] = _number(getattr(r, f))
    rec.update(_consistency(r, ok))
    diag = r.diagnostics or {}
    rec["frac_within_kmax"] = _number(diag.get("frac_within_kmax"))
    rec["collapsed"] = bool(_dict(diag.get("collapse")).get("collapsed"))
    v = r.versions or {}
    rec.update(device=v.get("device"), render_device=r.render_device, backend=v.get("backend"),
               renderer=v.get("renderer") or v.get("backend"), threads=_integer(_threads(r)),
               config_hash=r.config_hash or None, inputs_fingerprint=inputs_fingerprint(r),
               source=_dict(r.source).get("kind"), git=v.get("git"), path=str(path))
    return rec


def _identity(r: RunResult) -> dict[str, Any]:
    return {"method": r.method, "dataset": r.dataset, "scene": r.scene, "budget": r.budget,
            "cap": pattern_cap(r) if is_pattern(r) else None, "preset": r.preset, "seed": int(r.seed),
            "experiment": _text((r.config or {}).get("experiment_name"))}


def _reason(r: RunResult) -> str | None:
    return None if r.status == "ok" else (r.error or "no error recorded")


def _metric(r: RunResult, name: str) -> tuple[float | None, str | None]:
    """(value, why there is none): a recorded non-finite value is kept as recorded (NaN, inf)."""
    v = (r.metrics or {}).get(name)
    if v is not None:
        x = _number(v)
        return (x, None) if x is not None else (None, f"not a number ({v!r})")
    if name in (r.missing or {}):
        return None, str(r.missing[name])
    return None, NOT_RECORDED


def _consistency(r: RunResult, ok: bool) -> dict[str, Any]:
    """Table 4's scores (``result.consistency``): the value, or why not (``missing`` as recorded, not
    recorded, not a number); the FLIP under the key ``flip_name`` names (else ``flip``, then ``flip7``)."""
    c = r.consistency or {}
    out: dict[str, Any] = {"consistency_flow": None, "consistency_flip_name": None, "consistency_mask": None}
    if not c:
        return out
    out.update(consistency_flow=str(c.get("estimator") or c.get("flow") or "unknown"),
               consistency_flip_name=str(c.get("flip_name", "flip")),
               consistency_mask=None if c.get("mask") is None else str(c.get("mask")))
    for k in CONSISTENCY:
        key = c.get("flip_name", "flip") if k == "flip" else k
        v = c.get(key, c.get("flip7") if k == "flip" else None)
        x, why = None, None
        if isinstance(v, dict) and "missing" in v:
            why = str(v["missing"])
        elif v is None:
            why = NOT_RECORDED
        else:
            x = _number(v)
            why = None if x is not None else f"not a number ({v!r})"
        out[f"consistency_{k}"] = x
        out[f"consistency_{k}_missing"] = why if ok else None
    return out


def inputs_fingerprint(r: RunResult) -> str | None:
    """The digest of the fingerprint of the files a cell read (results.json's ``inputs``,
    ``smgs.data.fingerprint``); None where there is none: a result written before it was recorded, or
    a scene whose format lists no input files (``inputs["note"]`` says why)."""
    digest = _dict(r.inputs).get("digest")
    return None if digest is None else str(digest)


def _threads(r: RunResult) -> Any:
    """The CPU threads the cell trained with: a top-level ``threads`` field where recorded, else
    ``diagnostics["train_conditions"]["threads"]``."""
    t = (r.other_fields or {}).get("threads")
    return t if t is not None else _dict(_dict(r.diagnostics).get("train_conditions")).get("threads")


def _text(x: Any) -> str | None:
    return None if x is None else str(x)


def _dict(x: Any) -> dict:
    return x if isinstance(x, dict) else {}


def _number(x: Any) -> float | None:
    """``float(x)``, None for what is not a number; NaN and inf stay as recorded."""
    if x is None or isinstance(x, (dict, list)):
        return None
    try:
        return float(x)
    except (TypeError, ValueError):
        return None


def _integer(x: Any) -> int | None:
    f = _number(x)
    return int(f) if f is not None and f == f and abs(f) != float("inf") else None


def _at(values: Any, i: int) -> float | None:
    return _number(values[i]) if isinstance(values, list) and i < len(values) else None
