"""Checkpoints: loaded without running code, and never into a method of another config."""

import io

import pytest
import torch

from baselines import create_method
from baselines.splatting import CHECKPOINT
from smgs.data.patterns import pattern_scene
from smgs.train import pattern_config, to_dict


def _config(steps=6, **over):
    cfg = to_dict(pattern_config("3dgs", cap=4, steps=steps))
    cfg.update(over)
    return cfg


class _RunsCode:
    """Unpickling this calls ``open(marker, "w")``: a stand-in for any code a pickle can run."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_round_trip_loads_with_weights_only(tmp_path):
    scene = pattern_scene("circle4", 12)
    a = create_method("3dgs", scene, _config(), device="cpu")
    for s in range(3):
        a.train_step(s)
    a.save(tmp_path / "ck")
    # the file itself is loadable by the restricted unpickler
    torch.load(tmp_path / "ck" / CHECKPOINT, weights_only=True)
    b = create_method("3dgs", scene, _config(), device="cpu")
    b.load(tmp_path / "ck")
    assert b.describe()["step"] == 3


def test_a_checkpoint_that_runs_code_is_refused(tmp_path):
    scene = pattern_scene("circle4", 12)
    a = create_method("3dgs", scene, _config(), device="cpu")
    a.save(tmp_path / "ck")
    state = torch.load(tmp_path / "ck" / CHECKPOINT, weights_only=True)
    marker = tmp_path / "pwned"
    state["payload"] = _RunsCode(marker)
    buf = io.BytesIO()
    torch.save(state, buf)
    (tmp_path / "ck" / CHECKPOINT).write_bytes(buf.getvalue())
    b = create_method("3dgs", scene, _config(), device="cpu")
    with pytest.raises(ValueError, match=r"(?s)checkpoint\.pt.*refused.*code"):
        b.load(tmp_path / "ck")
    assert not marker.exists()


def test_a_checkpoint_of_another_config_is_refused(tmp_path):
    scene = pattern_scene("circle4", 12)
    a = create_method("3dgs", scene, _config(), device="cpu")
    a.train_step(0)
    a.save(tmp_path / "ck")
    other = _config()
    other["optim"]["means_lr"] *= 1000
    b = create_method("3dgs", scene, other, device="cpu")
    with pytest.raises(ValueError, match=r"another config.*optim\.means_lr"):
        b.load(tmp_path / "ck")
    with pytest.raises(ValueError, match=r"another config"):
        create_method("3dgs", scene, _config(steps=7), device="cpu").load(tmp_path / "ck")
