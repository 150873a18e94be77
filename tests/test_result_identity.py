"""A run's result is identified by its config and by the method's complete settings, defaults
included: after an update that changes a default (Softmax-GS's initial β went 20 → 1), a sweep
retrains instead of reporting a result computed under the old default as current."""

import dataclasses

from hydra import compose, initialize_config_dir

import baselines.splatting as splatting
from protocols.cell import result_hash
from protocols.run import CONFIG_DIR, plan
from smgs.train import ParamInit


def _cell(*overrides: str) -> dict:
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        _, payloads = plan(compose(config_name="config", overrides=list(overrides)), list(overrides))
    return payloads[0]["config"]


def test_a_changed_default_changes_the_result_hash(monkeypatch):
    cell = _cell("grid.datasets=[procedural]", "grid.methods=[softmax_gs]", "protocol=cpu")
    before = result_hash(cell)
    assert result_hash(dict(cell)) == before        # deterministic, the config alone unchanged
    real = splatting.from_dict

    def older_defaults(tp, d, **kw):                # the same config read by code with another default
        cfg = real(tp, d, **kw)
        return dataclasses.replace(cfg, gaussians=dataclasses.replace(cfg.gaussians, beta=ParamInit(20.0)))

    monkeypatch.setattr(splatting, "from_dict", older_defaults)
    assert result_hash(cell) != before


def test_the_resolved_settings_are_the_trainers_own():
    cell = _cell("grid.datasets=[procedural]", "grid.methods=[softmax_gs]", "protocol=cpu", "budget=5pct")
    from baselines.registry import resolved_settings
    from protocols.run_settings import method_settings, run_settings

    s = resolved_settings("softmax_gs", method_settings(cell), run_settings(cell))
    assert s["mode"] == "softmax_gs" and s["steps"] == 3000
    assert s["gaussians"]["beta"]["init"] == 1.0 and s["densify"]["grad_threshold"] == 0.004


def test_a_method_that_cannot_be_resolved_still_gets_a_hash():
    cell = _cell("grid.datasets=[procedural]", "grid.methods=[3dgs]")
    assert len(result_hash({**cell, "method": {"name": "no_such_method"}})) == 16


def test_the_2d_patterns_keep_their_own_initial_beta():
    """β from 20 on the 2D fits (their rate cannot grow it from 1 in 10K steps; config.py)."""
    from baselines.registry import resolved_settings
    from protocols.run_settings import method_settings, run_settings
    from smgs.train import pattern_config

    cell = _cell("+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]", "grid.methods=[softmax_gs]")
    s = resolved_settings("softmax_gs", method_settings(cell), run_settings(cell))
    assert s["gaussians"]["beta"]["init"] == 20.0 == pattern_config("softmax_gs", cap=4).gaussians.beta.init


def test_the_k_max_scope_is_part_of_the_identity_and_reaches_the_trainer():
    """method.train.k_max_scope (docs/kmax-scope.md) from the method yaml into the resolved settings
    (so the result hash) and the TrainConfig; an unknown scope is refused by name."""
    import pytest

    from baselines.registry import resolved_settings
    from protocols.run_settings import method_settings, run_settings
    from smgs.train.config import TrainConfig, from_dict

    base = ("grid.datasets=[procedural]", "grid.methods=[softmax_gs]", "protocol=cpu")
    pixel, patch = _cell(*base), _cell(*base, "method.train.k_max_scope=patch")
    assert pixel["method"]["train"]["k_max_scope"] == "pixel"
    s = resolved_settings("softmax_gs", method_settings(patch), run_settings(patch))
    assert s["k_max_scope"] == "patch"
    assert result_hash(pixel) != result_hash(patch)
    assert from_dict(TrainConfig, {"k_max_scope": "patch"}).k_max_scope == "patch"
    with pytest.raises((ValueError, TypeError), match="k_max_scope"):
        from_dict(TrainConfig, {"k_max_scope": "tile"})
