"""smgs sets torch's OpenMP threads to wait passively (unless the user chose), before torch loads:
spinning waiters cost several times the run time on a loaded machine (smgs/__init__.py)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# records the policy at the moment torch is first imported (OpenMP reads it when torch loads)
SPY = """
import os, sys
seen = []
class Spy:
    def find_spec(self, name, path=None, target=None):
        if name == "torch" and not seen:
            seen.append(os.environ.get("OMP_WAIT_POLICY"))
        return None
sys.meta_path.insert(0, Spy())
"""
PROBE = SPY + """
import {mod}
import torch
print(seen[0], "smgs" in sys.modules)
"""


def _policy(mod: str, preset: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if preset is not None:
        env["OMP_WAIT_POLICY"] = preset
    env["PYTHONPATH"] = str(ROOT)
    out = subprocess.run([sys.executable, "-c", PROBE.format(mod=mod)], env=env, cwd=ROOT,
                         capture_output=True, text=True, timeout=120, check=True)
    return out.stdout.split()


@pytest.mark.parametrize("mod", ["smgs", "protocols.cell", "bench.raster", "bench.train"])
def test_entry_points_set_passive_before_torch(mod):
    assert _policy(mod, None) == ["PASSIVE", "True"]


def test_a_users_choice_is_kept():
    assert _policy("smgs", "active") == ["active", "True"]


# bench/train_step.py's split (main) and its workers (Session, in the tree compared) up to the moment
# they would build the cell, and bench/ab.py's worker (no requests); the policy goes to stderr (the
# workers keep stdout for their answers)
STEP_PROBE = SPY + """
sys.path.insert(0, "bench")
import train_step
def stop(*a, **k):
    raise SystemExit(0)
train_step.build = stop
try:
    {call}
except SystemExit:
    pass
print(seen[0], file=sys.stderr)
"""


@pytest.mark.parametrize("call", ["train_step.main(['protocol=cpu'])", "train_step.Session(['protocol=cpu'], 0)",
                                  "import ab; ab.worker('.')"])
def test_the_ab_benches_time_the_policy_smgs_runs_with(call):
    """bench/train_step.py (the split, and each tree's worker) and bench/ab.py's workers import the
    tree's smgs before torch, so that each tree is timed with the OpenMP wait policy ``smgs run`` has;
    importing torch first timed them with spinning waiters, which share the cores with the renderer's
    own threads."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    env["PYTHONPATH"] = str(ROOT)
    out = subprocess.run([sys.executable, "-c", STEP_PROBE.format(call=call)], env=env, cwd=ROOT, input="",
                         capture_output=True, text=True, timeout=120, check=True)
    assert out.stderr.split()[-1:] == ["PASSIVE"], out.stderr[-2000:]
