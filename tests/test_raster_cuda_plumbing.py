"""The CUDA backend's Python side, without a GPU.

* Importing ``smgs.raster.cuda`` and asking for the backend never raises; on a machine without a
  CUDA build of torch or without a device it is unavailable with a reason, and ``auto`` keeps the
  reference for CUDA tensors and the cpu backend for CPU tensors.
* The argument plumbing between the autograd Function and the torch binding: a stand-in extension
  takes its parameter names, types and order from the binding's C++ source (cuda_binding.cpp: the
  C++ signatures and their py::arg names) and its output order from the binding's documented return
  list, computes with the reference backend, and the wrapper's images and gradients must equal the
  reference's. A swapped argument, a misplaced saved tensor or a misrouted gradient fails here.
"""

import re
from pathlib import Path

import pytest
import torch

from smgs.raster import backend_available, rasterize_splats, resolve_backend
from smgs.raster import constants as K
from smgs.raster import cuda as cuda_backend
from smgs.raster.reference import rasterize_splats_reference
from smgs.raster.types import MODES, mode_flags

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
    body = re.search(r"enum \{([^}]*)\}", (CSRC / "cuda_kernel.h").read_text()).group(1)
    names = [s.split("=")[0].strip() for s in body.split(",")]
    return {n: i for i, n in enumerate(names)}


def test_binding_signatures_and_pybind_names_agree():
    for fn, name in (("forward_torch", "forward"), ("backward_torch", "backward")):
        params = cpp_params(fn)
        assert [n for _, n in params] == py_args(name), fn
        assert all(t in PYTYPE for t, _ in params), params
    assert len(returned("forward_torch")) == 11
    ret = re.search(r"return \{(rgb, [^}]*)\};", BINDING).group(1)
    assert len(ret.split(",")) == len(returned("forward_torch"))


def test_cuda_backend_unavailable_without_a_cuda_build_or_device():
    if torch.version.cuda is not None and torch.cuda.is_available():
        pytest.skip("a CUDA device is present: tests/test_raster_cuda.py covers the backend")
    assert cuda_backend.is_available() is False
    reason = cuda_backend.unavailable_reason()
    assert reason and ("CUDA" in reason or "SMGS_DISABLE_CUDA_BACKEND" in reason)
    assert not backend_available("cuda", "cuda", torch.float32)
    assert not backend_available("cuda", "cpu", torch.float32)
    assert resolve_backend("auto", "cuda", torch.float32) == "reference"
    with pytest.raises(RuntimeError):
        resolve_backend("cuda", "cuda", torch.float32)
    with pytest.raises(RuntimeError, match="unavailable"):
        cuda_backend.extension()


class StandInExtension:
    """The binding's contract, computed by the reference backend on CPU tensors."""

    def __init__(self):
        self.P = pk_layout()
        self.calls = []

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
        out = rasterize_splats_reference(
            ins["means2d"], ins["conics"], ins["opacities"], ins["colors"], ins["depths"], ins["alpha"],
            ins["beta"], ins["gamma"], v["width"], v["height"],
            mode={(False, False): "3dgs", (True, False): "gef_only", (False, True): "softmax_only",
                  (True, True): "softmax_gs"}[(v["use_gef"], v["use_softmax"])],
            k_max=v["k_max"], background=opt(v["background"]), eq15="solved" if v["solved"] else "printed",
            reg_values=ins.get("reg_values"), reg_depth_scale=v["reg_scale"],
            k_max_scope="patch" if v["patch"] else "pixel")
        return out, ins

    def forward(self, *args):
        v = self._bind("forward_torch", args)
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


def scene(n=12, w=21, h=17, n_ch=3, n_reg=0, seed=0):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    sc = dict(means2d=r(n, 2) * torch.tensor([w, h]), conics=torch.stack([0.2 + 0.3 * r(n), 0.05 * (r(n) - 0.5),
                                                                           0.2 + 0.3 * r(n)], 1),
              opacities=0.3 + 0.6 * r(n), colors=r(n, n_ch), depths=1 + 3 * r(n), alpha=0.5 + 2 * r(n),
              beta=8 * r(n), gamma=2 * r(n))
    if n_reg:
        sc["reg_values"] = r(n, n_reg)
    return sc


def run(fn, sc, w, h, mode, **kw):
    names = KEYS + (["reg_values"] if "reg_values" in sc else [])
    ins = {k: sc[k].clone().requires_grad_(True) for k in names}
    bg = torch.tensor([0.2, 0.5, 0.7][:sc["colors"].shape[1]], requires_grad=True)
    out = fn(*[ins[k] for k in KEYS], w, h, mode, kw.pop("k_max", 3), bg, kw.pop("eq15", "solved"),
             ins.get("reg_values"), kw.pop("reg_depth_scale", 1.0), K.T_MIN, kw.pop("scope", "pixel"))
    g = torch.Generator().manual_seed(9)
    loss = sum((t * torch.rand(t.shape, generator=g)).sum() for t in (out.rgb, out.alpha, out.depth))
    if out.reg is not None:
        loss = loss + (out.reg * torch.rand(out.reg.shape, generator=g)).sum()
    loss.backward()
    return out, {**{k: t.grad for k, t in ins.items()}, "background": bg.grad}


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("n_ch,n_reg,eq15,scope", [(3, 0, "solved", "pixel"), (1, 2, "printed", "pixel"),
                                                   (3, 1, "solved", "patch")])
def test_wrapper_plumbing_matches_the_reference(mode, n_ch, n_reg, eq15, scope):
    sc = scene(n_ch=n_ch, n_reg=n_reg)
    ext = StandInExtension()

    def via_wrapper(*a):
        return cuda_backend.composite(ext, *a)

    def via_reference(m2, co, op, col, de, al, be, ga, w, h, mode, k_max, bg, eq, rv, rs, t_min, scope):
        return rasterize_splats_reference(m2, co, op, col, de, al, be, ga, w, h, mode=mode, k_max=k_max,
                                          background=bg, eq15=eq, reg_values=rv, reg_depth_scale=rs, t_min=t_min,
                                          k_max_scope=scope)

    ow, gw = run(via_wrapper, sc, 21, 17, mode, eq15=eq15, reg_depth_scale=0.6, scope=scope)
    orf, gr = run(via_reference, sc, 21, 17, mode, eq15=eq15, reg_depth_scale=0.6, scope=scope)
    assert ext.calls == ["forward_torch", "backward_torch"]
    for a, b in ((ow.rgb, orf.rgb), (ow.alpha, orf.alpha), (ow.depth, orf.depth)):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert (ow.reg is None) == (orf.reg is None)
    if ow.reg is not None:
        torch.testing.assert_close(ow.reg, orf.reg, rtol=0, atol=0)
    assert torch.equal(ow.stats.n_contrib, orf.stats.n_contrib) and ow.stats.k_max == orf.stats.k_max
    assert ow.stats.scope == orf.stats.scope == scope
    assert (ow.stats.list_end is None) == (scope == "pixel")
    if scope == "patch":
        assert torch.equal(ow.stats.list_end, orf.stats.list_end)
    assert ow.stats.pairs_evaluated == 12345
    use_gef, use_soft = mode_flags(mode)
    for k, want in gr.items():
        got = gw[k]
        if want is None:
            assert got is None or (got == 0).all(), k
            continue
        # the same reference graph on both sides, so equal bits; the background's gradient is the
        # wrapper's Σ g_rgb·T with T = 1 - alpha from the stand-in, against autograd's product T
        tol = 1e-5 if k == "background" else 0.0
        torch.testing.assert_close(got, want, rtol=tol, atol=tol, msg=k)
    assert (gw["alpha"] is None) == (not use_gef) and (gw["beta"] is None) == (not use_soft)
