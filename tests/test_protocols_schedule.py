"""The 3DGS densification schedule follows the protocol's step count (gsplat's steps_scaler)."""

from hydra import compose, initialize_config_dir

from baselines.trainer_settings import train_config
from protocols.run import CONFIG_DIR, plan
from protocols.run_settings import method_settings, run_settings


def cell_train_config(*overrides: str) -> dict:
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(config_name="config", overrides=list(overrides))
        _, payloads = plan(cfg, list(overrides))
    cell = payloads[0]["config"]
    return train_config(method_settings(cell), run_settings(cell))


def test_cpu_preset_scales_the_schedule_and_never_resets_at_the_end():
    mc = cell_train_config("+experiment=budget5", "protocol=cpu", "grid.datasets=[procedural]")
    d = mc["densify"]
    assert mc["steps"] == 3000
    assert (d["refine_start"], d["refine_stop"], d["refine_every"], d["reset_every"]) == (50, 1500, 10, 300)
    assert mc["sh_degree_interval"] == 100
    # opacity resets happen only while refining, so the last one leaves half the run to recover
    last_reset = max(i for i in range(1, d["refine_stop"]) if i % d["reset_every"] == 0)
    assert last_reset <= mc["steps"] // 2


def test_paper_protocol_keeps_the_3dgs_schedule():
    mc = cell_train_config("+experiment=budget5", "protocol=paper", "grid.datasets=[procedural]")
    d = mc["densify"]
    assert mc["steps"] == 30000
    assert d.get("refine_stop", 15000) == 15000 and d.get("reset_every", 3000) == 3000


def test_a_dataset_with_its_own_steps_keeps_its_schedule():
    mc = cell_train_config("+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]")
    assert mc["steps"] == 10000
    assert mc["densify"]["refine_stop"] == 10000 and mc["densify"].get("reset_every") is None


def test_smoke_keeps_the_unscaled_schedule_so_it_does_not_refine():
    mc = cell_train_config("+experiment=smoke", "grid.methods=[3dgs]")
    assert mc["steps"] == 300
    assert mc["densify"].get("refine_start", 500) >= 300
