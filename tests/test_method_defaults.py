"""The trainer's defaults a built-in method's config shows (k_max, k_max_scope, eq15, the
hyperparameter set) have one home, TrainConfig: the method YAMLs take them from the Hydra group
method/train (protocols/method_defaults.py) instead of restating them, and the composed config and
`smgs run --help` still show them to override."""

import subprocess
import sys
from pathlib import Path

from hydra import compose, initialize_config_dir

from baselines import BUILTINS
from protocols.method_defaults import SHOWN, register, trainer_defaults
from protocols.run import CONFIG_DIR
from smgs.train.config import TrainConfig

ROOT = Path(__file__).resolve().parents[1]


def _train_section(method: str) -> dict:
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return dict(compose(config_name="config", overrides=[f"method={method}"]).method.train)


def test_no_builtin_method_config_restates_them_and_each_shows_the_codes_values():
    code = TrainConfig()
    for name in BUILTINS:
        text = (Path(CONFIG_DIR) / "method" / f"{name}.yaml").read_text()
        restated = [k for k in (*SHOWN, "optim") if f"\n  {k}:" in text or f"\n{k}:" in text]
        assert restated == [], (name, restated)
        shown = _train_section(name)
        assert {k: shown[k] for k in SHOWN} == {k: getattr(code, k) for k in SHOWN}
        assert shown["optim"] == code.optim.name


def test_a_default_changed_in_the_code_is_what_the_configs_show(monkeypatch):
    monkeypatch.setattr(TrainConfig, "k_max", 64)
    try:
        register()
        assert trainer_defaults()["k_max"] == 64 and _train_section("softmax_gs")["k_max"] == 64
    finally:
        monkeypatch.undo()
        register()
    assert _train_section("softmax_gs")["k_max"] == 128


def test_the_composed_config_shows_them_to_override():
    """``smgs run --cfg job`` (Hydra's print of the composed config, which ``smgs run --help`` names)."""
    out = subprocess.run([sys.executable, "-m", "protocols.run", "--cfg", "job"], capture_output=True, text=True,
                         cwd=ROOT, timeout=300, check=True).stdout
    assert "  train:\n    k_max: 128\n    k_max_scope: pixel\n    eq15: solved\n" in out
