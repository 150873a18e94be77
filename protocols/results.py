"""The results.json of one run: schema, atomic writing, reading.

One run = one cell of an experiment grid (method × dataset/scene × budget × seed). The runner writes
``results.json`` once, atomically, when the run ends (ok or failed); reports read every
``results.json`` below a directory. Nothing here depends on Hydra.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from smgs.atomic import atomic_write_text

SCHEMA_VERSION = 1
RESULTS_FILE = "results.json"
POINTER = "checkpoint.json"   # in a run directory: which checkpoint is its last


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
    schema: int = SCHEMA_VERSION

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "RunResult":
        d = dict(d)
        if d.get("schema", SCHEMA_VERSION) > SCHEMA_VERSION:
            raise ValueError(f"results schema {d['schema']} is newer than this smgs ({SCHEMA_VERSION})")
        d["curve"] = [CurvePoint(**c) for c in d.get("curve", [])]
        known = RunResult.__dataclass_fields__
        unknown = set(d) - set(known)
        if unknown:
            raise ValueError(f"unknown fields in results: {sorted(unknown)}")
        return RunResult(**d)


def config_hash(config: dict) -> str:
    """Stable hash of a resolved config (key order does not matter)."""
    blob = json.dumps(config, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


def write_result(run_dir: Path | str, result: RunResult) -> Path:
    path = Path(run_dir) / RESULTS_FILE
    atomic_write_text(path, json.dumps(result.to_dict(), indent=1, default=_json_default))
    return path


def read_result(path: Path | str) -> RunResult:
    path = Path(path)
    try:
        return RunResult.from_dict(json.loads(path.read_text()))
    except (json.JSONDecodeError, TypeError, ValueError) as e:
        raise ValueError(f"{path}: not a valid smgs results file ({e})") from e


def find_results(root: Path | str) -> list[Path]:
    return sorted(Path(root).rglob(RESULTS_FILE))


def _json_default(o):
    if hasattr(o, "item"):
        return o.item()
    if hasattr(o, "tolist"):
        return o.tolist()
    return str(o)
