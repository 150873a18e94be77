"""A check that every tensor a block of code creates lives on one device.

On a CPU-only machine a forgotten ``device=`` is invisible: the tensor lands on the CPU, which is
the run's device too. So the check makes torch's default device ``meta`` for the block: any
factory call without an explicit device (``torch.zeros(n)``, ``torch.tensor(x)``, ...) then makes
a meta tensor, and a dispatch mode sees every operator's output and records each tensor that is
not on the run's device, with the line of our code that made it. On a GPU run the same forgotten
``device=`` would have made a CPU tensor.

Not seen by the check: ``torch.from_numpy`` (always the CPU, not an operator) and tensors made
before the block (e.g. a scene loaded from disk: data, moved to the run's device by the trainer).
"""

from __future__ import annotations

import traceback
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

REPO = Path(__file__).resolve().parent.parent


def _our_frame() -> str:
    """The innermost stack frame in this repository's code (not torch's, not this file's)."""
    for fr in reversed(traceback.extract_stack()[:-2]):
        p = Path(fr.filename).resolve()
        if REPO in p.parents and p.name != Path(__file__).name:
            return f"{p.relative_to(REPO)}:{fr.lineno} {fr.line}"
    return "(no frame in this repository)"


class _Recorder(TorchDispatchMode):
    def __init__(self, device: torch.device) -> None:
        super().__init__()
        self.device = device
        self.strays: list[str] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        for t in tree_leaves(out):
            if isinstance(t, torch.Tensor) and t.device != self.device:
                where = f"{func} -> {t.device}: {_our_frame()}"
                if where not in self.strays:
                    self.strays.append(where)
        return out


class StrayTensors(AssertionError):
    pass


@contextmanager
def only_device(device: torch.device | str) -> Iterator[_Recorder]:
    """Fail (StrayTensors) if the block creates a tensor on another device than ``device``, or if
    it errs because one of its tensors was made on the decoy default device."""
    dev = torch.device(device)
    rec = _Recorder(dev)
    try:
        with torch.device("meta"), rec:
            yield rec
    except Exception as e:
        if rec.strays:
            raise StrayTensors(f"tensors created off {dev}:\n  " + "\n  ".join(rec.strays)) from e
        raise
    if rec.strays:
        raise StrayTensors(f"tensors created off {dev}:\n  " + "\n  ".join(rec.strays))


def fit_config(method: str, steps: int = 40) -> dict:
    """A 2D fit that clones, splits, prunes and resets opacities within a few steps, on a random
    background: every path of a training step that makes tensors."""
    from smgs.train import pattern_config, to_dict

    cfg = to_dict(pattern_config(method, cap=12, steps=steps))
    cfg["densify"].update(refine_start=1, refine_every=3, reset_every=6)
    cfg["gaussians"].update(flat_spacing=0.05, flat_scale=0.1)
    cfg["random_background"] = True
    return cfg


def train_save_load(method: str, scene, first, second, path: Path, steps: int = 8):
    """Train ``steps`` steps on device ``first``, save, and load the checkpoint into a fresh method
    on ``second``; returns (trained, loaded)."""
    from baselines import create_method

    a = create_method(method, scene, fit_config(method), device=first)
    for s in range(steps):
        a.train_step(s)
    a.save(path)
    b = create_method(method, scene, fit_config(method), device=second)
    b.load(path)
    return a, b
