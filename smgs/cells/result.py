"""The results.json of one run: schema, atomic writing, reading.

One run = one cell of an experiment grid (method × dataset/scene × budget × seed). The runner
(protocols/) writes ``results.json`` once, atomically, when the run ends (ok or failed); the results
table (``smgs.results``) and the reports read every ``results.json`` below a directory. Here, in the
library, so that reading results needs neither the runner nor Hydra; ``protocols.results`` adds the
runner's own names (which config keys change a result, the config hash).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from smgs.atomic import atomic_write_text

SCHEMA_VERSION = 1
RESULTS_FILE = "results.json"


@dataclass
class CurvePoint:
    """An evaluation during training, for error-against-time curves."""

    step: int
    seconds: float          # train wall-clock seconds so far, evaluation excluded
    psnr: float
    num_gaussians: int


@dataclass
class RunResult:
    """Everything a report needs about one run.

    status: "ok", "failed" (``error`` says why) or "skipped" (``error`` says why, e.g. missing data).
    metrics: dataset-protocol means over the test views: psnr, ssim, lpips, flip (a key is absent
        when the metric could not be computed; ``missing`` then names the reason).
    per_view: per-test-view lists, same keys as metrics plus "name".
    preset: "paper" for the paper's protocol, or the name of a reduced preset (e.g. "cpu") that a
        report must label as such.
    source: where the model came from when this run did not train it (``kind: "pretrained"``,
        ``ply``, ``sha256``, ``trained_here: false``; ``protocols.evaluate_ply``); empty when the
        run trained it.
    inputs: the fingerprint of the scene's files the run read (``smgs.data.fingerprint``: ``files``
        name -> size and sha256, ``digest``, ``folder``; ``files`` null with a ``note`` where the
        format lists none); empty in results written before it was recorded.
    config_hash: the cell's identity (``smgs.identity.cell_key``), with ``inputs`` what a rerun
        compares to skip it and the report to pool its seeds.
    """

    method: str
    dataset: str
    scene: str
    budget: str
    seed: int
    status: str = "ok"
    error: str | None = None
    preset: str = "paper"
    config: dict = field(default_factory=dict)
    config_hash: str = ""
    hparams: str = ""
    metrics: dict[str, float] = field(default_factory=dict)
    lpips_net: str | None = None
    missing: dict[str, str] = field(default_factory=dict)
    per_view: dict[str, list] = field(default_factory=dict)
    num_gaussians: int | None = None
    train_seconds: float | None = None
    build_seconds: float | None = None   # building/loading the compiled kernels, never in train_seconds
    render_fps: float | None = None
    render_device: str | None = None
    peak_memory_mb: float | None = None
    steps: int | None = None
    curve: list[CurvePoint] = field(default_factory=list)
    diagnostics: dict[str, Any] = field(default_factory=dict)
    consistency: dict[str, Any] = field(default_factory=dict)
    versions: dict[str, str] = field(default_factory=dict)
    data: dict[str, Any] = field(default_factory=dict)
    source: dict[str, Any] = field(default_factory=dict)
    inputs: dict[str, Any] = field(default_factory=dict)
    schema: int = SCHEMA_VERSION
    # fields this smgs does not know (added by a newer one within the same schema): kept, written back
    other_fields: dict[str, Any] = field(default_factory=dict, repr=False)

    def to_dict(self) -> dict:
        d = asdict(self)
        other = d.pop("other_fields")
        return {**{k: v for k, v in other.items() if k not in d}, **d}

    @staticmethod
    def from_dict(d: dict) -> "RunResult":
        d = dict(d)
        schema = d.get("schema", SCHEMA_VERSION)
        if not isinstance(schema, int) or isinstance(schema, bool):
            raise ValueError(f"results schema {schema!r} is not a schema number")
        if schema > SCHEMA_VERSION:
            raise NewerResults(schema)
        d["curve"] = [CurvePoint(**c) for c in d.get("curve", [])]
        known = set(RunResult.__dataclass_fields__) - {"other_fields"}
        other = {k: d.pop(k) for k in sorted(set(d) - known)}
        return RunResult(**d, other_fields=other)


class NewerResults(ValueError):
    """A results file of a newer schema than this smgs reads: it is left as it is, never rewritten."""

    def __init__(self, schema: int, path: Path | None = None):
        self.schema = schema
        where = "" if path is None else f"{path}: "
        super().__init__(f"{where}written by a newer smgs (results schema {schema}; this smgs reads schema "
                         f"{SCHEMA_VERSION}): upgrade smgs to read it or to rerun its cell")


def write_result(run_dir: Path | str, result: RunResult) -> Path:
    path = Path(run_dir) / RESULTS_FILE
    atomic_write_text(path, json.dumps(result.to_dict(), indent=1, default=_json_default))
    return path


def read_result(path: Path | str) -> RunResult:
    path = Path(path)
    try:
        return RunResult.from_dict(json.loads(path.read_text()))
    except NewerResults as e:
        raise NewerResults(e.schema, path) from None
    except (json.JSONDecodeError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: not a valid smgs results file ({e})") from e


def find_results(root: Path | str) -> list[Path]:
    """Every results.json below ``root``, except those in hidden folders (a rerun's work in progress
    beside a finished cell, ``protocols.cell_rerun``; a report being built)."""
    root = Path(root)
    return sorted(p for p in root.rglob(RESULTS_FILE)
                  if not any(part.startswith(".") for part in p.relative_to(root).parts[:-1]))


def _json_default(o):
    if hasattr(o, "item"):
        return o.item()
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)
