"""Every executor produces the same results tree."""

import pytest

from protocols.results import find_results, read_result
from protocols.run import run_experiment

ARGS = ["+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]", "grid.scenes=[circle4]",
        "grid.methods=[3dgs,gef_only]", "dataset.size=16", "dataset.steps=6", "report=false",
        "eval.fps_repeats=1", "eval.flip=false"]


def tree(root):
    out = {}
    for p in find_results(root):
        r = read_result(p)
        out[str(p.relative_to(root))] = (r.status, r.config_hash, round(r.metrics["psnr"], 4))
    return out


@pytest.mark.parametrize("kind", ["local", "submitit_local"])
def test_executor_gives_the_same_results_tree_as_sequential(tmp_path, kind):
    run_experiment(ARGS + [f"out_dir={tmp_path}/seq"])
    s = run_experiment(ARGS + [f"out_dir={tmp_path}/{kind}", f"executor.kind={kind}", "executor.workers=2"])
    assert [x["status"] for x in s] == ["ok", "ok"]
    assert tree(tmp_path / kind) == tree(tmp_path / "seq")
