"""The ``smgs`` command: ``smgs --help`` lists every subcommand, and each subcommand reaches the
module that does the work, in this process (a tiny smoke run, its report, its PLY out and back in,
the lists, a benchmark, the popping scenes)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from protocols.results import read_result
from smgs_cli.main import COMMANDS, main

REPO = Path(__file__).resolve().parent.parent
CONFIGS = REPO / "configs"
SCENE = ["dataset.width=32", "dataset.height=24", "dataset.n_views=8", "eval.fps_repeats=1", "eval.flip=false"]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    out = tmp_path_factory.mktemp("runs")
    assert main(["run", "+experiment=smoke", "protocol.steps=4", "eval.fractions=[1.0]", "report=false",
                 "grid.methods=[3dgs]", *SCENE, f"out_dir={out}"]) == 0
    return out


def run_dir(out: Path, budget: str = "full") -> Path:
    return out / "procedural" / "blocks" / "3dgs" / budget / "seed0"


def test_help_lists_every_subcommand_and_the_package_installs_the_command(capsys):
    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    names = [c.name for c in COMMANDS]
    assert names == ["run", "report", "results", "evaluate", "export", "render", "list", "bench", "popping", "lpips-weights",
                     "download"]
    assert all(f"\n  {n} " in text and f"smgs {n} " in text for n in names)
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts == {"smgs": "smgs_cli.main:main"}


def test_a_closed_pipe_stops_the_command_quietly():
    """``smgs --help | head -1``: the reader has gone before the help is written. The command
    stops with the shell's status for a closed pipe (141) and no traceback."""
    import os
    import subprocess
    import sys

    read, write = os.pipe()
    os.close(read)   # nobody reads: the first write fails with EPIPE
    try:
        done = subprocess.run([sys.executable, "-c", "import sys; from smgs_cli.main import main; sys.exit(main())",
                               "--help"], stdout=write, stderr=subprocess.PIPE, cwd=REPO, timeout=120, text=True)
    finally:
        os.close(write)
    assert done.returncode == 141, done.stderr
    assert "Traceback" not in done.stderr and "BrokenPipe" not in done.stderr, done.stderr


def test_no_or_an_unknown_command_is_a_usage_error(capsys):
    assert main([]) == 2
    assert main(["frobnicate"]) == 2
    assert "unknown command 'frobnicate'; the commands are run, report" in capsys.readouterr().err


def test_run_runs_the_grid(runs):
    r = read_result(run_dir(runs) / "results.json")
    assert r.status == "ok" and r.method == "3dgs" and r.steps == 4


def test_run_refuses_a_dataset_path_without_its_kind(capsys):
    with pytest.raises(SystemExit) as e:
        main(["run", "+experiment=budget5", "dataset.path=/my/capture"])
    assert e.value.code == 2 and "add dataset=colmap" in capsys.readouterr().err


def test_report_builds_the_report(runs, capsys):
    assert main(["report", str(runs), "--no-stability"]) == 0
    assert (runs / "report" / "report.md").is_file() and (runs / "report" / "report.html").is_file()
    assert f"report: {runs / 'report' / 'report.md'}" in capsys.readouterr().out


def test_export_then_evaluate_the_ply(runs, tmp_path):
    ply = tmp_path / "model.ply"
    assert main(["export", str(run_dir(runs)), "--out", str(ply)]) == 0
    assert ply.stat().st_size > 0
    assert main(["evaluate", str(ply), f"out_dir={runs}", "report=false", *SCENE]) == 0
    r = read_result(run_dir(runs, "pretrained") / "results.json")
    assert r.status == "ok" and r.source["trained_here"] is False


@pytest.mark.parametrize("name", [c.name for c in COMMANDS])
def test_every_command_answers_help_with_status_0(name, capsys):
    try:
        code = main([name, "--help"])
    except SystemExit as e:   # argparse and Hydra stop with SystemExit(0) after their help
        code = e.code
    assert code in (0, None)
    assert capsys.readouterr().out.strip()


def test_evaluate_help_lists_its_options(capsys):
    assert main(["evaluate", "--help"]) == 0
    text = capsys.readouterr().out
    assert all(o in text for o in ("MODEL.ply", "dataset=", "dataset.path=", "scene=", "protocol=", "out_dir=",
                                   "report=false", "--force"))
    assert main(["evaluate"]) == 2 and "error: no model given" in capsys.readouterr().err


def test_help_names_everything_smgs_list_lists(capsys):
    """``smgs --help``'s line for ``list`` names what ``smgs list`` takes (it once left out the
    strategies and renderers ``smgs list`` had gained)."""
    assert main(["--help"]) == 0
    assert "smgs list {methods,experiments,datasets,budgets,protocols,strategies,renderers}" in capsys.readouterr().out


def test_list_descriptions_end_with_a_sentence(capsys):
    """A config's description is whole sentences of its opening comment, never a line cut off
    where the comment wraps (mcmc's ended "... with the MCMC strategy at the")."""
    for what in ("experiments", "datasets", "budgets", "protocols"):
        assert main(["list", what]) == 0
        for line in capsys.readouterr().out.splitlines():
            name, about = line.split(maxsplit=1)
            block = " ".join(x.lstrip("#").strip() for x in (CONFIGS / what[:-1] / f"{name}.yaml").read_text()
                             .split("\n\n")[0].splitlines() if x.startswith("#") and "@package" not in x)
            assert block.startswith(about) and (about == block or about[-1] in ".!?"), (what, line)
    assert main(["list", "experiments"]) == 0
    assert "at the paper's cap on Mip-NeRF360 (2593000, the 3DGS count there); 30K steps." in capsys.readouterr().out


@pytest.mark.parametrize("what, has", [("methods", "softmax_gs"), ("experiments", "budget5"),
                                       ("datasets", "colmap"), ("budgets", "5pct"), ("protocols", "cpu"),
                                       ("strategies", "mcmc"), ("renderers", "cuda")])
def test_list_names_what_a_command_line_can_name(what, has, capsys):
    assert main(["list", what]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert any(line.split()[0] == has and len(line.split()) > 1 for line in lines)


def test_list_of_something_else_is_a_usage_error(capsys):
    assert main(["list", "scenes"]) == 2
    assert "smgs list {methods,experiments,datasets,budgets,protocols,strategies,renderers}" in capsys.readouterr().err


def test_bench_runs_a_benchmark_of_the_checkout(tmp_path, capsys):
    assert main(["bench", "ply", "--n", "2000", "--degree", "0", "--repeats", "1", "--dir", str(tmp_path)]) == 0
    assert "2000" in capsys.readouterr().out
    assert main(["bench", "nope"]) == 2
    assert main(["bench"]) == 2
    listed = capsys.readouterr().out.split("benchmarks: ")[1].split(", ")
    assert {"raster", "train", "ply"} <= {n.strip() for n in listed}
    assert not {"gpu_stages", "gpu_report"} & {n.strip() for n in listed}   # modules the GPU check imports


def test_a_benchmark_that_stops_with_a_message_prints_it(capsys):
    """bench/raster.py stops on an unknown scene with SystemExit(message): `smgs bench` prints the
    message (as `python -m bench.raster` does) and returns 1."""
    assert main(["bench", "raster", "--scenes", "no_such_scene", "--backends", "reference", "--repeats", "1"]) == 1
    assert "no_such_scene" in capsys.readouterr().err


def test_popping_writes_its_tables(tmp_path):
    assert main(["popping", str(tmp_path)]) == 0
    assert (tmp_path / "popping.md").is_file() and (tmp_path / "popping.csv").is_file()


def test_lpips_weights_reaches_its_module(capsys):
    with pytest.raises(SystemExit) as e:
        main(["lpips-weights", "--help"])
    assert e.value.code == 0 and "lpips_<net>.pth" in capsys.readouterr().out
