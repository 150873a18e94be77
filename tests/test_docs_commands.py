"""Every command in README.md and docs/ runs as written: each command of a fenced ```bash block is
run here on the project's small scenes, with the short-run settings appended where it trains
(tests/doc_commands.py: the collection, the substitution rule, the order), and must exit 0. A
command that cannot run here is in ``CANNOT_RUN`` with why; an entry that no longer matches a
documented command fails, so the list cannot outlive what it excuses.

One child process runs them all (an ``smgs`` or ``python -m`` command in that process, through the
``smgs`` command's own entry, ``smgs_cli.main.main``; anything else through bash), each distinct
command once: commands that differ only in what the short run replaces share their runs, and a run
finished by an earlier command is skipped as ``smgs run`` skips it. 55 s of CPU time on the project's
2-core AMD EPYC (1.6 to 1.9 min of wall time there at load 5 to 6).

To add a documented command: nothing, if it can run here; else one line in ``CANNOT_RUN``.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from doc_commands import REPO, SCENES, SHORT, DocCommand, collect, module_commands, order, plan

CANNOT_RUN: dict[str, str] = {
    # installing: the environment these tests run in is installed by CI's own install step (.ci/run)
    "pip install torch==2.13.0": "downloads torch (on Linux x86-64 PyPI's CUDA build, 2.7 GB) into the "
                                 "environment the tests run in",
    "pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu": "downloads torch's CPU build "
                                                                                 "(192 MB)",
    "pip install --no-build-isolation -e .": "installs this checkout into the environment the tests run in",
    'pip install --no-build-isolation -e ".[test]"': "installs this checkout into the environment the tests run in",
    "python -m pytest": "the test suite this test is part of",
    # a GPU
    "python -m pytest -m gpu": "needs a CUDA GPU (without one every GPU test skips)",
    "smgs run +experiment=smoke device=cuda": "needs a CUDA GPU (without one it stops: tests/test_run_command_line.py)",
    "smgs run +experiment=budget5 device=cuda:1": "needs two CUDA GPUs and the paper's datasets",
    'smgs run +experiment=patterns "grid.budgets=[cap4,cap16]" device=cuda': "needs a CUDA GPU",
    "python -m bench.train --device cuda --scenes pattern256 scene3d": "needs a CUDA GPU",
    "python bench/raster.py --backends cuda cpu --modes 3dgs softmax_gs": "needs a CUDA GPU",
    # a download
    "smgs download mipnerf360 tandt deepblending": "downloads the paper's datasets (tens of GB; the command is "
                                                   "tested against a local server: tests/test_download.py)",
    "smgs download mipnerf360 --scenes bicycle,garden": "downloads Mip-NeRF360 (12 GB)",
    "smgs download tandt --from-file ~/tandt_db.zip": "needs the T&T archive fetched by hand (650 MB)",
    "smgs run +experiment=budget5": "needs the paper's datasets (smgs download)",
    "smgs run +experiment=budget5 protocol=cpu": "needs the paper's datasets (smgs download)",
    "smgs run +experiment=full on_missing=skip": "needs at least one of the paper's scenes (smgs download); with "
                                                 "none it stops, saying where it looked",
    "smgs run +experiment=full executor.kind=local executor.workers=2": "needs the paper's datasets (smgs download)",
    "smgs evaluate output/garden/point_cloud/iteration_30000/point_cloud.ply dataset=mipnerf360 scene=garden "
    "experiment_name=full": "needs a model the original 3DGS code trained on garden, and Mip-NeRF360 (smgs download)",
    # a cluster
    "smgs run +experiment=smoke executor.kind=slurm executor.slurm.partition=debug device=cpu":
        "needs a SLURM cluster: tests/test_slurm_executor.py runs this command, read from the page, on the "
        "single-node test cluster",
    "smgs run +experiment=full executor.kind=slurm executor.slurm.partition=gpu device=cuda "
    "executor.slurm.timeout_min=600 executor.slurm.cpus_per_task=8 executor.slurm.mem_gb=32":
        "needs a SLURM cluster with GPUs and the paper's datasets",
    # a plugin the page writes
    "smgs run grid.datasets=[my_capture] +dataset.path=/data/lab +dataset.frames=50 grid.methods=[3dgs,softmax_gs]":
        "needs the page's example scene-format plugin (my_capture) installed",
    "smgs run +method.train.densify.strategy=prune_faint +method.train.densify.threshold=0.02 "
    "grid.methods=[3dgs,softmax_gs]": "needs the page's example strategy plugin (prune_faint) installed",
}


def canonical(text: str) -> str:
    """The command with ``python -m MODULE`` written as the ``smgs`` command that fronts it (the
    two are the same program: one entry of ``CANNOT_RUN`` covers both)."""
    m = re.match(r"python -m ([\w.]+)(.*)", text)
    if m and m.group(1) in module_commands():
        return f"smgs {module_commands()[m.group(1)]}{m.group(2)}"
    return text


def is_environment(cmd: DocCommand) -> bool:
    """``export NAME=VALUE``: sets the environment of the block's later commands (doc_commands)."""
    return re.fullmatch(r"export \w+=\S+", cmd.text) is not None


COMMANDS = collect()
RUNNABLE = [c for c in COMMANDS if canonical(c.text) not in CANNOT_RUN and not is_environment(c)]


def _fixture_absent(cmd: DocCommand) -> str | None:
    kind = re.search(r"\bdataset=(\w+)", cmd.text)
    needs = SCENES.get(kind.group(1)) if kind and "dataset.path=" in cmd.text else None
    if needs is not None and not needs.is_dir():
        return f"fixture {needs} absent (CI keeps ../shared beside the checkout)"
    return None


def _writes(cmd: DocCommand) -> str | None:
    """The runs folder a training command writes (``runs/<experiment_name>``), None for another."""
    text = canonical(cmd.text)
    if not text.startswith(("smgs run ", "smgs evaluate ")) or "out_dir=" in text:
        return None
    name = re.search(r"(?:\+experiment|experiment_name)=(\w+)", text)
    return f"runs/{name.group(1) if name else 'default'}"


def _missing_fixture(cmd: DocCommand) -> str | None:
    """Why ``cmd`` cannot run without the fixture scenes: it reads one, or it reads the runs folder
    that only commands reading one write."""
    absent = _fixture_absent(cmd)
    if absent:
        return absent
    folder = next((t for t in cmd.text.split() if t.startswith("runs/")), None)
    if folder is None:
        return None
    folder = "/".join(folder.split("/")[:2])
    writers = [c for c in RUNNABLE if _writes(c) == folder]
    if writers and all(_fixture_absent(c) for c in writers):
        return f"{folder} comes from `{writers[0].text}`: {_fixture_absent(writers[0])}"
    return None


@pytest.fixture(scope="module")
def ran(tmp_path_factory) -> dict[str, tuple[int | None, Path | None]]:
    """Every runnable command's exit status and log, by its place (``page:line text``)."""
    work = tmp_path_factory.mktemp("docs")
    jobs: list[dict] = []
    index: dict[str, int] = {}
    job_of: dict[str, int | None] = {}
    for c in order(RUNNABLE):
        if _missing_fixture(c):
            job_of[f"{c.where} {c.text}"] = None
            continue
        for job in plan(c, work):
            if job.key() not in index:
                index[job.key()] = len(jobs)
                jobs.append({"argv": job.argv, "shell": job.shell, "env": job.env})
        job_of[f"{c.where} {c.text}"] = index[job.key()]
    (work / "jobs.json").write_text(json.dumps(jobs, indent=1))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
           "PATH": os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")])}
    try:   # a generous ceiling: the commands that ended before it keep their status
        subprocess.run([sys.executable, str(REPO / "tests" / "doc_commands.py"), str(work)], cwd=work, env=env,
                       timeout=1800, check=False)
    except subprocess.TimeoutExpired:
        pass
    status = json.loads((work / "status.json").read_text()) if (work / "status.json").exists() else {}
    return {k: (None, None) if j is None else ((status.get(str(j)) or [None])[0], work / "logs" / f"{j}.log")
            for k, j in job_of.items()}


@pytest.mark.parametrize("cmd", RUNNABLE, ids=[f"{c.where} {c.text}" for c in RUNNABLE])
def test_a_documented_command_runs_as_written(cmd, ran):
    missing = _missing_fixture(cmd)
    if missing:
        pytest.skip(missing)
    rc, log = ran[f"{cmd.where} {cmd.text}"]
    tail = log.read_text()[-3000:] if log is not None and log.exists() else "(no log: the run stopped before it)"
    assert rc == 0, (f"{cmd.where}: `{cmd.text}` exited {rc}:\n{tail}\n(a command that cannot run here: one line in "
                     f"CANNOT_RUN, {canonical(cmd.text)!r}: \"why\")")


def test_every_command_that_cannot_run_here_is_still_documented_and_says_why():
    documented = {canonical(c.text) for c in COMMANDS}
    stale = [k for k in CANNOT_RUN if k not in documented]
    assert not stale, f"CANNOT_RUN excuses commands no page has any more: {stale}"
    assert all(len(why) > 10 for why in CANNOT_RUN.values())


def test_the_pages_have_commands_and_the_collection_reads_them_as_written():
    texts = {c.text for c in COMMANDS}
    assert "smgs run +experiment=smoke" in texts   # the README's main job, after its install
    assert ("smgs evaluate point_cloud.ply dataset=colmap dataset.path=/my/capture" in texts
            and "pip install --no-build-isolation -e ." in texts)   # a `&&` chain is its commands
    continued = [c for c in COMMANDS if c.text.startswith("smgs run +experiment=full executor.kind=slurm")
                 or "executor.kind=slurm" in c.text]
    assert continued and all("\\" not in c.text and "#" not in c.text for c in COMMANDS)


def test_the_short_run_appended_is_the_one_the_docs_state():
    """docs/usage.md ("Short runs") says what these runs append; it must be what they append."""
    usage = " ".join((REPO / "docs" / "usage.md").read_text().replace("`", "").split())
    assert " ".join(SHORT) in usage
