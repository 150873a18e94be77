"""The results.json of one run, as the runner names it: the schema, writing and reading live in the
library (``smgs.cells.result``, one reader for the runner, the results table and the reports); here
the runner's own additions: which config keys do not change a result, the config hash, the
checkpoint pointer's name.
"""

from __future__ import annotations

import hashlib
import json

from smgs.atomic import atomic_write_text
from smgs.cells.result import (RESULTS_FILE, SCHEMA_VERSION, CurvePoint, NewerResults, RunResult, find_results,
                              read_result, write_result)

__all__ = ["RESULTS_FILE", "SCHEMA_VERSION", "POINTER", "VOLATILE", "CurvePoint", "NewerResults", "RunResult",
           "atomic_write_text", "config_hash", "find_results", "read_result", "write_result"]

POINTER = "checkpoint.json"   # in a run directory: which checkpoint is its last
# Keys of a cell's config that do not change its result (where and how it runs).
VOLATILE = ("force", "executor", "report", "report_builder", "out_dir", "data_root", "on_missing", "grid",
            "seeds", "experiment_name", "checkpoint_every", "export_ply", "on_busy")


def config_hash(config: dict) -> str:
    """Stable hash of a resolved config (key order does not matter)."""
    blob = json.dumps(config, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]
