"""A cell's training config is made once and passed down: the checks before the sweep, the result's
hash and the method all read the TrainConfig made when the cell was planned
(``protocols.run_settings.cell_settings``), and the method's fixed settings are merged once."""

import baselines.registry as registry
from smgs.train.config import TrainConfig


def test_each_cell_builds_its_train_config_and_resolves_its_method_config_once(tmp_path, monkeypatch):
    from protocols.run import run_experiment

    built, merged = [], []
    real_init, real_resolve = TrainConfig.__init__, registry.resolve_config

    def counting_init(self, *args, **kwargs):
        built.append(1)
        real_init(self, *args, **kwargs)

    def counting_resolve(name, config=None):
        merged.append(name)
        return real_resolve(name, config)

    monkeypatch.setattr(TrainConfig, "__init__", counting_init)
    monkeypatch.setattr(registry, "resolve_config", counting_resolve)
    summaries = run_experiment(["+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]",
                                "grid.scenes=[circle4]", "grid.methods=[3dgs,softmax_gs]", "dataset.size=16",
                                "dataset.steps=4", "report=false", "eval.fps_repeats=1", "eval.flip=false",
                                f"out_dir={tmp_path}"])
    assert [s["status"] for s in summaries] == ["ok", "ok"], summaries
    assert len(built) == 2            # one TrainConfig per cell, from planning to the trained method
    assert sorted(merged) == ["3dgs", "softmax_gs"]
