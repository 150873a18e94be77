"""One definition of a cell's identity (smgs.identity): what skips a finished cell, matches a
checkpoint and pools seeds. Settings that change no number (a CUDA kernel set or glue on a CPU run,
also from the environment; eval.viewer_views) neither retrain a finished cell nor split a pooled
row; every result hashed before keeps its hash (or, where a no-number key was set, is still taken
as this cell's), so an upgrade retrains nothing whose numbers it does not change."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir

from counting_method import counting  # noqa: F401 (the fixture)
from protocols.cell import result_key
from protocols.run import CONFIG_DIR, plan, run_experiment
from smgs import identity
from smgs.raster import backends

CONFIGS = {   # cells of each kind of dataset, with and without the settings the identity leaves out
    "procedural": ("+experiment=smoke", "grid.methods=[softmax_gs]", "grid.seeds_of={}"),
    "colmap": ("dataset=colmap", "dataset.path=/data/fern", "grid.methods=[3dgs]", "budget=5pct"),
    "patterns": ("+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]", "grid.scenes=[circle4]",
                 "grid.methods=[gef_only]"),
}


def _cell(*overrides: str, device: str = "cpu") -> dict:
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        _, payloads = plan(compose(config_name="config", overrides=list(overrides)), list(overrides))
    return {**payloads[0]["config"], "device": device}


def hash_as_9235246(cfg: dict) -> str:
    """protocols.cell.result_hash as 9235246 wrote it (before smgs.identity), the reference every
    finished result's config_hash was made with."""
    from protocols.run_settings import cell_settings
    from protocols.sections import BudgetConfig
    from smgs.raster.backends import is_default
    from smgs.train.config import earlier_train_keys

    ident = {k: v for k, v in cfg.items() if k not in identity.VOLATILE}
    section = cfg.get("renderer")
    if not section or (isinstance(section, dict) and all(is_default(k, v) for k, v in section.items())):
        ident.pop("renderer", None)
    ident["budget"] = BudgetConfig.of(cfg).identity()
    resolved = cell_settings(cfg).resolved
    if resolved is not None:
        ident["resolved_settings"] = earlier_train_keys(resolved)
    return identity.config_hash(ident)


@pytest.fixture(autouse=True)
def _no_variant_in_the_environment(monkeypatch):
    for k in (backends.KERNELS_ENV, backends.GLUE_ENV):
        monkeypatch.delenv(k, raising=False)


@pytest.mark.parametrize("kind", CONFIGS)
@pytest.mark.parametrize("device", ["cpu", "cuda:0"])
def test_a_result_hashed_before_keeps_its_hash(kind, device):
    cfg = _cell(*CONFIGS[kind], device=device)
    key = result_key(cfg)
    assert key.hash == hash_as_9235246(cfg) and key.earlier == ()


@pytest.mark.parametrize("extra", [["eval.viewer_views=1"], ["eval.save_renders=false"],
                                   ["renderer.kernels=v2", "renderer.glue=lean"]])
def test_a_setting_that_changes_no_number_changes_no_cpu_cell(extra):
    cfg, other = _cell(*CONFIGS["procedural"]), _cell(*CONFIGS["procedural"], *extra)
    key = result_key(other)
    assert key.hash == result_key(cfg).hash
    assert hash_as_9235246(other) in (key.hash, *key.earlier)   # a result of it hashed before is this cell's
    assert key.mismatch(hash_as_9235246(other), None) is None
    assert identity.pooling_key(other) == identity.pooling_key(cfg)


def test_a_cuda_variant_exported_in_the_environment_changes_no_cpu_cell(monkeypatch):
    before = result_key(_cell(*CONFIGS["procedural"])).hash
    monkeypatch.setenv(backends.KERNELS_ENV, "v2")
    monkeypatch.setenv(backends.GLUE_ENV, "lean")
    cfg = _cell(*CONFIGS["procedural"])
    assert cfg["renderer"] == {"kernels": "v2", "glue": "lean"} and result_key(cfg).hash == before
    cuda = _cell(*CONFIGS["procedural"], device="cuda:0")   # there it renders otherwise: another cell
    assert result_key(cuda).hash != result_key({**cuda, "renderer": {}}).hash


def test_what_changes_numbers_is_still_another_cell():
    base = _cell(*CONFIGS["procedural"])
    for extra in ("eval.quantize=false", "protocol.steps=20", "method.train.k_max=64", "seed=1"):
        assert result_key(_cell(*CONFIGS["procedural"], extra)).hash != result_key(base).hash, extra
    assert identity.pooling_key(_cell(*CONFIGS["procedural"], "seed=1")) == identity.pooling_key(base)
    moved = _cell(*CONFIGS["colmap"][:1], "dataset.path=/elsewhere/fern", *CONFIGS["colmap"][2:])
    colmap = _cell(*CONFIGS["colmap"])
    assert result_key(moved).hash != result_key(colmap).hash          # hashed: a moved scene reruns
    assert identity.pooling_key(moved) == identity.pooling_key(colmap)   # pooled: its fingerprint compares


def test_the_keys_that_change_no_number_are_named_once_with_their_defaults():
    """NO_NUMBER's defaults are configs/config.yaml's (a hash at another default would change every
    finished cell's); each of its keys, VOLATILE's and LOCATIONS' sections exist in a composed cell."""
    cfg = yaml.safe_load((Path(CONFIG_DIR) / "config.yaml").read_text())
    for key, default in identity.NO_NUMBER.items():
        section, name = key.split(".")
        assert cfg[section][name] == default, key
    cell = _cell(*CONFIGS["colmap"])
    assert set(identity.VOLATILE) <= set(cell) and {k.split(".")[0] for k in identity.LOCATIONS} <= {"dataset", "ply"}
    import protocols.results
    import reports.runs

    assert protocols.results.VOLATILE is identity.VOLATILE
    assert reports.runs.seed_config.__module__ == "reports.runs"   # the reports' name, delegating here
    flat = identity.pooling_key(cell)
    assert not {*identity.NO_NUMBER, *identity.LOCATIONS, "seed"} & set(flat) and flat["device"] == "'cpu'"


def test_a_changed_input_is_a_mismatch_that_names_the_file():
    fp = {"files": {"images/a.png": {"size": 3, "sha256": "aa"}, "images/b.png": {"size": 3, "sha256": "bb"}},
          "digest": "d1"}
    changed = {"files": {"images/a.png": {"size": 3, "sha256": "cc"}, "images/c.png": {"size": 3, "sha256": "bb"}},
               "digest": "d2"}
    key = identity.CellKey("h", inputs=changed)
    assert key.mismatch("h", fp) == ("the inputs changed since it was computed: images/a.png (changed), "
                                     "images/b.png (gone), images/c.png (new)")
    assert key.mismatch("h", {}) is None                          # recorded before inputs were
    assert key.mismatch("h", {"digest": "d2"}) is None            # a checkpoint records the digest only
    assert "their digest d1 is now d2" in key.mismatch("h", {"digest": "d1"})
    assert key.mismatch("other", changed).startswith("its config other is not this cell's h")


def test_finished_cells_are_not_retrained_for_a_setting_that_changes_no_number(tmp_path, counting, monkeypatch):
    """End to end on a tiny cell: finished once; then the same with a CUDA variant on the CPU (asked,
    and exported), another number of viewer views: skipped each time, nothing trained. A results.json
    that an earlier smgs hashed (viewer views set, so its hash was not today's) is skipped too."""
    tiny = ["+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]", "grid.scenes=[circle4]",
            "dataset.size=16", "dataset.steps=4", "report=false", "eval.fps_repeats=1", "eval.flip=false",
            "grid.methods=[counting]", "device=cpu", f"out_dir={tmp_path}"]
    assert run_experiment(tiny + ["eval.viewer_views=2"])[0]["status"] == "ok"
    for extra in (["renderer.kernels=v2", "renderer.glue=lean"], ["eval.viewer_views=1"], ["exported"]):
        if extra == ["exported"]:
            monkeypatch.setenv(backends.KERNELS_ENV, "v2")
            extra = []
        counting.calls.clear()
        s = run_experiment(tiny + extra)
        assert s[0].get("skipped") and counting.calls == [], extra
    monkeypatch.delenv(backends.KERNELS_ENV)
    res = tmp_path / "patterns/circle4/counting/cap4/seed0/results.json"
    d = json.loads(res.read_text())
    assert d["config_hash"] != hash_as_9235246(d["config"])
    d["config_hash"] = hash_as_9235246(d["config"])   # as the earlier smgs recorded it
    res.write_text(json.dumps(d))
    s = run_experiment(tiny + ["eval.viewer_views=2"])
    assert s[0].get("skipped") and counting.calls == []


def test_a_checkpoint_resumes_whatever_cuda_variant_a_cpu_run_asked(tmp_path, counting):
    """A CPU cell interrupted under renderer.kernels=v2 resumes from its checkpoint without it: the
    cell's identity and the method's check of the checkpoint's config agree on what changes nothing."""
    tiny = ["+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]", "grid.scenes=[circle4]",
            "dataset.size=16", "dataset.steps=6", "report=false", "eval.fps_repeats=1", "eval.flip=false",
            "grid.methods=[counting]", "device=cpu", "checkpoint_every=2", f"out_dir={tmp_path}"]
    counting.interrupt_at = 3
    with pytest.raises(KeyboardInterrupt):
        run_experiment(tiny + ["renderer.kernels=v2", "renderer.glue=lean"])
    counting.calls.clear()
    s = run_experiment(tiny)
    assert s[0]["status"] == "ok", s
    assert counting.calls == [2, 3, 4, 5]


def test_seeds_differing_only_in_what_changes_no_number_are_pooled():
    """Before: eval.viewer_views, or a CUDA kernel set asked on a CPU run, split a pooled row."""
    from protocols.results import RunResult
    from reports.runs import config_difference

    def seed(s: int, *extra: str) -> RunResult:
        cfg = _cell(*CONFIGS["procedural"], f"seed={s}", *extra)
        return RunResult("softmax_gs", "procedural", "blocks", "full", s, config=cfg, hparams="3dgs2023+softmaxgs")

    assert config_difference([seed(0), seed(1, "eval.viewer_views=0"), seed(2, "renderer.kernels=v2"),
                              seed(3, "eval.save_renders=false")]) is None
    assert config_difference([seed(0), seed(1, "protocol.steps=20")]).startswith(
        "seeds trained under different configs, not pooled: protocol.steps (seed 0: 300; seed 1: 20)")
