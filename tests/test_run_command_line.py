"""``smgs run``'s command line: its own --help (not Hydra's config dump), the KEY=VALUE hint for a
setting written as a flag, and every refusal in one block with exit status 2 before anything is
written (Hydra's <out_dir>/_hydra/run.log included)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from protocols.config_files import config_names
from smgs_cli.listing import LISTED
from smgs_cli.main import COMMANDS, main

REPO = Path(__file__).resolve().parent.parent


def test_run_help_shows_the_runs_own_options(capsys):
    assert main(["run", "--help"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("usage: smgs run [+experiment=NAME] [KEY=VALUE ...] [--force]")
    assert all(f"\n  {name} " in text for name in config_names("experiment"))
    for key in ("dataset.path=DIR", "protocol.steps", "device ", "out_dir ", "grid.* ", "executor.* ", "eval.* ",
                "--force", "--cfg job", "docs/usage.md"):
        assert key in text, key
    assert "Powered by Hydra" not in text and "== Config ==" not in text and len(text.splitlines()) < 80


@pytest.mark.parametrize("args, hint", [(["--protocol.steps", "300"], "protocol.steps=300"),
                                        (["--steps=30"], "steps=30"), (["--seed"], "seed=VALUE")])
def test_a_setting_written_as_a_flag_gets_the_key_value_hint(args, hint, capsys):
    with pytest.raises(SystemExit) as e:
        main(["run", "+experiment=smoke", *args])
    assert e.value.code == 2
    assert f"settings are written KEY=VALUE, without dashes: {hint}" in capsys.readouterr().err


def test_a_refused_setting_exits_2_in_one_block_and_writes_nothing(tmp_path):
    out = tmp_path / "runs"
    p = subprocess.run([sys.executable, "-m", "protocols.run", "+experiment=smoke", "+steps=30", f"out_dir={out}"],
                       cwd=REPO, capture_output=True, text=True, timeout=300)
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip() == ("error: invalid config, nothing was run:\n  +steps=30: no setting is called steps, so "
                                "nothing would read it; did you mean protocol.steps=30? (settings: smgs run --help)")
    assert not out.exists()   # not even Hydra's _hydra/run.log


def test_a_device_that_is_not_there_is_refused_before_hydra_writes_its_log(tmp_path, capsys):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA: device=cuda would run")
    out = tmp_path / "runs"
    with pytest.raises(SystemExit) as e:
        main(["run", "+experiment=smoke", "device=cuda", f"out_dir={out}"])
    assert e.value.code == 2 and "device=cuda asks for CUDA" in capsys.readouterr().err
    assert not out.exists()


def test_hydras_own_errors_are_refusals_too(capsys):
    with pytest.raises(SystemExit) as e:
        main(["run", "+experiment=nope"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "Could not find 'experiment/nope'" in err and "budget5" in err
    assert "Traceback" not in err and "HYDRA_FULL_ERROR" not in err


# ---- answers at once ------------------------------------------------------------------------------

CPU_SECONDS = 1.0   # what a simple question may cost in CPU time (torch's import alone is about 1.1 s here)
QUICK = [["list", what] for what in LISTED] + [["--help"]] + [[c.name, "--help"] for c in COMMANDS]   # new ones too


def cpu_seconds_of(args: list[str]) -> float:
    """The CPU time (user + system, not the wall clock: a loaded machine stretches that) a child
    process running ``smgs ARGS`` takes, and that it exits 0."""
    import resource

    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    p = subprocess.run([sys.executable, "-m", "smgs_cli", *args], cwd=REPO, capture_output=True, text=True, timeout=300)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    assert p.returncode == 0 and p.stdout.strip(), p.stderr
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


@pytest.mark.parametrize("args", QUICK, ids=" ".join)
def test_a_simple_question_answers_in_well_under_a_second_of_cpu_time(args):
    """``smgs list budgets`` took 10 s and ``smgs report --help`` 15 s on a loaded machine: they
    imported torch, Hydra and the renderer to print a list or a usage text."""
    assert cpu_seconds_of(args) < CPU_SECONDS, args
