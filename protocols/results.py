"""The results.json of one run, as the runner names it: the schema, writing and reading live in the
library (``smgs.cells.result``, one reader for the runner, the results table and the reports); the
keys that change no result and the config hash with a cell's identity (``smgs.identity``); here the
checkpoint pointer's name.
"""

from __future__ import annotations

from smgs.atomic import atomic_write_text
from smgs.cells.result import (RESULTS_FILE, SCHEMA_VERSION, CurvePoint, NewerResults, RunResult, find_results,
                              read_result, write_result)
from smgs.identity import VOLATILE, config_hash

__all__ = ["RESULTS_FILE", "SCHEMA_VERSION", "POINTER", "VOLATILE", "CurvePoint", "NewerResults", "RunResult",
           "atomic_write_text", "config_hash", "find_results", "read_result", "write_result"]

POINTER = "checkpoint.json"   # in a run directory: which checkpoint is its last
