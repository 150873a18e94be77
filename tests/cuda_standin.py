"""The CUDA binding's contract without a GPU: its parameters and outputs read from
``csrc/cuda_binding.cpp`` (the C++ signatures, their ``py::arg`` names and the documented return
lists), and a stand-in extension that honours that contract by computing with a CPU renderer
(the reference by default: tests/test_raster_cuda_plumbing.py checks the wrapper's plumbing to the
bit; tests/device_mix.py uses the compiled CPU backend, for speed).

The stand-in also reports the host synchronisations the real binding makes (``syncs``): its
forward reads the pair count (``offs[N-1].item()``, which sizes the tile list) and its backward
reads the most crowded pixel's count only in the softmax modes. tests/test_raster_syncs.py checks
these against the binding's source.
"""

import re
from pathlib import Path

import torch

from smgs.raster import constants as K
from smgs.raster import cuda as cuda_backend
from smgs.raster.composite_inputs import CompositeSettings, Splats2D
from smgs.raster.reference import rasterize_splats_reference

CSRC = Path(cuda_backend.__file__).parent / "csrc"
BINDING = (CSRC / "cuda_binding.cpp").read_text()
KEYS = ["means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma"]
PYTYPE = {"at::Tensor": torch.Tensor, "int64_t": int, "bool": bool, "double": float}


def cpp_params(fn: str) -> list[tuple[str, str]]:
    """(C++ type, name) of each parameter of a binding function, in order."""
    m = re.search(rf"std::vector<at::Tensor> {fn}\((.*?)\)\s*\{{", BINDING, re.S)
    assert m, fn
    params = [" ".join(p.split()) for p in m.group(1).split(",")]
    return [tuple(p.rsplit(" ", 1)) for p in params]


def py_args(name: str) -> list[str]:
    m = re.search(rf'm\.def\("{name}",(.*?)\);', BINDING, re.S)
    assert m, name
    return re.findall(r'py::arg\("(\w+)"\)', m.group(1))


def returned(fn: str) -> list[str]:
    """The documented output list of a binding function (the comment above it)."""
    m = re.search(rf"// Returns \[([^\]]*)\][^\n]*\n(?://[^\n]*\n)*std::vector<at::Tensor> {fn}\(", BINDING)
    assert m, fn
    return [s.strip() for s in m.group(1).replace("//", "").split(",")]


def pk_layout() -> dict[str, int]:
    body = re.search(r"enum \{([^}]*)\}", (CSRC / "packed_row.h").read_text()).group(1)
    names = [s.split("=")[0].strip() for s in body.split(",")]
    return {n: i for i, n in enumerate(names)}


class StandInExtension:
    """The binding's contract, computed by the reference backend on CPU tensors."""

    def __init__(self, render=rasterize_splats_reference):
        self.P = pk_layout()
        self.calls = []
        self.render = render

    def _bind(self, fn, args):
        params = cpp_params(fn)
        assert len(args) == len(params), f"{fn}: {len(args)} arguments for {len(params)} parameters"
        for (t, n), a in zip(params, args):
            want = PYTYPE[t]
            ok = isinstance(a, want) and (want is not int or not isinstance(a, bool))
            assert ok, f"{fn}: parameter {n} ({t}) got {type(a).__name__}"
        self.calls.append(fn)
        return {n: a for (_, n), a in zip(params, args)}

    def _render(self, v, grad):
        opt = lambda t: None if t.numel() == 0 else t  # noqa: E731
        ins = {k: (v[k].detach().clone().requires_grad_(grad) if v.get(k) is not None else None)
               for k in KEYS + ["reg_values"]}
        st = CompositeSettings(v["width"], v["height"], v["use_gef"], v["use_softmax"], v["k_max"], v["solved"],
                               v["reg_scale"], K.T_MIN, v["patch"])
        out = self.render(Splats2D(*(ins[k] for k in KEYS), background=opt(v["background"]),
                                   reg_values=ins.get("reg_values")), st)
        return out, ins

    def forward(self, *args):
        v = self._bind("forward_torch", args)
        self.given = dict(v)
        for k in ("alpha", "beta", "gamma", "reg_values"):
            v[k] = None if v[k].numel() == 0 else v[k]
        out, _ = self._render(v, grad=False)
        n, P = v["means2d"].shape[0], self.P
        nch, R = v["colors"].shape[1], 0 if v["reg_values"] is None else v["reg_values"].shape[1]
        pk = torch.zeros(n, P["P_COL"] + nch + R)
        for col, k in ((P["P_MX"], "means2d"), (P["P_CA"], "conics")):
            pk[:, col:col + v[k].shape[1]] = v[k]
        for col, k, default in ((P["P_O"], "opacities", 0), (P["P_D"], "depths", 0), (P["P_AL"], "alpha", 1),
                                (P["P_BE"], "beta", 0), (P["P_GA"], "gamma", 0)):
            pk[:, col] = default if v[k] is None else v[k]
        pk[:, P["P_COL"]:P["P_COL"] + nch] = v["colors"]
        if R:
            pk[:, P["P_COL"] + nch:] = v["reg_values"]
        tiles = -(-v["width"] // K.TILE_SIZE) * -(-v["height"] // K.TILE_SIZE)
        outs = dict(rgb=out.rgb, alpha=out.alpha, depth=out.depth,
                    reg=out.reg if R else torch.zeros(v["height"], v["width"], 0),
                    n_contrib=out.stats.n_contrib.int(), T_final=1 - out.alpha,
                    # `last` is the list end the kernel reports (1 + the last composited list position)
                    last=(torch.full_like(out.alpha, 7) if out.stats.list_end is None else out.stats.list_end).int(),
                    pairs=torch.tensor([12345]), pk=pk, ranges=torch.full((tiles, 2), 3, dtype=torch.int32),
                    tile_list=torch.arange(5, dtype=torch.int32))
        self.saved = outs
        return [outs[k] for k in returned("forward_torch")]

    def backward(self, *args):
        v = self._bind("backward_torch", args)
        s, P = self.saved, self.P
        for k in ("alpha_out", "depth_out", "T_final", "last", "n_contrib", "pk", "ranges", "tile_list"):
            ref = s[{"alpha_out": "alpha", "depth_out": "depth"}.get(k, k)]
            assert torch.equal(v[k], ref), f"backward got the wrong tensor as {k}"
        assert v["head_budget_bytes"] > 0
        pk, nch, R = v["pk"], v["n_channels"], v["n_reg"]
        assert pk.shape == (v["n"], P["P_COL"] + nch + R)
        ins = dict(means2d=pk[:, P["P_MX"]:P["P_MY"] + 1], conics=pk[:, P["P_CA"]:P["P_CC"] + 1],
                   opacities=pk[:, P["P_O"]], depths=pk[:, P["P_D"]], colors=pk[:, P["P_COL"]:P["P_COL"] + nch],
                   alpha=pk[:, P["P_AL"]] if v["use_gef"] else None,
                   beta=pk[:, P["P_BE"]] if v["use_softmax"] else None,
                   gamma=pk[:, P["P_GA"]] if v["use_softmax"] else None,
                   reg_values=pk[:, P["P_COL"] + nch:] if R else None)
        with torch.enable_grad():   # autograd runs Function.backward without grad mode
            out, leaves = self._render({**v, **ins}, grad=True)
            loss = (out.rgb * v["g_rgb"]).sum() + (out.alpha * v["g_alpha"]).sum() \
                + (out.depth * v["g_depth"]).sum()
            if R:
                loss = loss + (out.reg * v["g_reg"]).sum()
        names = KEYS + ["reg_values"]
        live = [leaves[k] for k in names if leaves.get(k) is not None]
        gs = dict(zip([k for k in names if leaves.get(k) is not None],
                      torch.autograd.grad(loss, live, allow_unused=True)))
        n = v["n"]
        zero = {"colors": torch.zeros(n, nch), "reg_values": torch.zeros(n, R), "means2d": torch.zeros(n, 2),
                "conics": torch.zeros(n, 3)}
        return [gs.get(k) if gs.get(k) is not None else zero.get(k, torch.zeros(n)) for k in names]
