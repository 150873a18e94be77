"""The opt-in CUDA kernels' bindings (csrc/projection_cuda_binding.cpp, csrc/cuda_v2_binding.cpp)
without a GPU: their parameters and outputs read from the C++ sources (the signatures, their
py::arg names and the documented return lists), and stand-in extensions that honour those contracts
by computing with the PyTorch oracles (``_Project``, ``eval_sh``, the reference compositing) on CPU
tensors: no compaction (culled rows zeros with radii (0, 0)), rows with radii (0, 0) never
composited, the backward's packed [N, S] gradient. tests/test_raster_cuda_v2_plumbing.py checks the
Python glue through them; tests/test_raster_cuda_v2_syncs.py runs them on a stand-in device.
"""

from __future__ import annotations

import re
from pathlib import Path

import torch

from smgs.raster import constants as K
from smgs.raster import cuda_v2
from smgs.raster.composite_inputs import CompositeSettings, Splats2D
from smgs.raster.projection import _Project, _View
from smgs.raster.reference import rasterize_splats_reference
from smgs.raster.sh import eval_sh

CSRC = Path(cuda_v2.__file__).parent / "csrc"
PYTYPE = {"at::Tensor": torch.Tensor, "int64_t": int, "bool": bool, "double": float, "std::vector<double>": list,
          "std::vector<at::Tensor>": list, "std::vector<int64_t>": list}
LAYOUT = [0, 1, 2, 4, 5, 6, 7, 8, 9, 10]   # packed_row.h's P_* (test_raster_cuda_v2_plumbing checks them)
KEYS = ("means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma")


def _settings(v: dict, **kw) -> CompositeSettings:
    """The compositing settings a binding call carries (t_min is compiled in: the default)."""
    return CompositeSettings(v["width"], v["height"], v["use_gef"], v["use_softmax"], v["k_max"], v["solved"],
                             v.get("reg_scale", 1.0), K.T_MIN, v["patch"], **kw)


def params(src: str, fn: str) -> list[tuple[str, str]]:
    m = re.search(rf"std::vector<at::Tensor> {fn}\((.*?)\)\s*\{{", src, re.S)
    assert m, fn
    return [tuple(" ".join(p.split()).rsplit(" ", 1)) for p in m.group(1).split(",")]


def py_args(src: str, name: str) -> list[str]:
    m = re.search(rf'm\.def\("{name}",(.*?)\);', src, re.S)
    assert m, name
    return re.findall(r'py::arg\("(\w+)"\)', m.group(1))


def returned(src: str, fn: str) -> list[str]:
    m = re.search(rf"// Returns \[([^\n]*)\]\.?\n(?://[^\n]*\n)*std::vector<at::Tensor> {fn}\(", src)
    assert m, fn
    return [re.sub(r"\s*\[.*|\s*\(.*", "", s).strip() for s in re.split(r",\s*(?![^\[]*\])", m.group(1))]


class _Bound:
    def __init__(self, src: str):
        self.src, self.calls = src, []

    def bind(self, fn: str, args) -> dict:
        ps = params(self.src, fn)
        assert len(args) == len(ps), f"{fn}: {len(args)} arguments for {len(ps)} parameters"
        for (t, n), a in zip(ps, args):
            want = PYTYPE[t]
            assert isinstance(a, want) and (want is not int or not isinstance(a, bool)), \
                f"{fn}: parameter {n} ({t}) got {type(a).__name__}"
        self.calls.append(fn)
        return {n: a for (_, n), a in zip(ps, args)}


def _view(cam: list[float]) -> tuple[_View, torch.Tensor]:
    f = torch.tensor(cam, dtype=torch.float32)
    return _View(f[:9].reshape(3, 3), f[9:12], f[12:14], f[14:16], f[16:18], f[18:20], f[20:22]), f[22:25]


class StandInProjection(_Bound):
    """projection_cuda_binding.cpp's contract through ``_Project`` and ``eval_sh``."""

    def __init__(self):
        super().__init__((CSRC / "projection_cuda_binding.cpp").read_text())

    def _compute(self, v, leaves):
        view, center = _view(v["camera"])
        means3d, quats, scales, sh = leaves
        n = means3d.shape[0]
        ids, m2, con, dep, rad = _Project.apply(means3d, quats, scales, view, v["near_plane"], v["eps2d"])
        full = lambda t, k: torch.zeros(n, k, dtype=t.dtype).index_copy(0, ids, t.reshape(-1, k))  # noqa: E731
        out = dict(means2d=full(m2, 2), conics=full(con, 3), depths=full(dep, 1)[:, 0], radii=full(rad, 2))
        if sh is not None:
            d = means3d[ids] - center
            d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            col = eval_sh(v["sh_degree"], sh[ids], d) + 0.5
            out["colours"] = full(col.clamp_min(0.0) if v["clamp"] else col, sh.shape[2])
        else:
            out["colours"] = torch.zeros(0, 0)
        return out

    def forward(self, *args):
        v = self.bind("project_forward_torch", args)
        sh = v["sh"] if v["sh"].numel() else None
        out = self._compute(v, (v["means3d"], v["quats"], v["scales"], sh))
        out["bad"] = torch.zeros(0, dtype=torch.int32)
        if v["check_inputs"]:   # the kernel's checks (projection_cuda.h ProjChecks): bad rows culled, flagged
            bad = self.bad_rows(v, sh)
            for k in ("means2d", "conics", "depths", "radii", "colours"):
                if out[k].numel():
                    out[k] = torch.where(bad.reshape(-1, *[1] * (out[k].dim() - 1)), 0.0, out[k])
            bg = v["background"]
            out["bad"] = torch.tensor([int(bool(bad.any()) or not bool(torch.isfinite(bg).all()))], dtype=torch.int32)
        return [out[k] for k in returned(self.src, "project_forward_torch")]

    @staticmethod
    def bad_rows(v: dict, sh: torch.Tensor | None) -> torch.Tensor:
        n = v["means3d"].shape[0]
        rows = lambda t: t.reshape(n, -1)  # noqa: E731
        ok = torch.isfinite(torch.cat([rows(v["means3d"]), rows(v["quats"]), rows(v["scales"])], 1)).all(1)
        ok &= (v["scales"] >= 0).all(1)
        if sh is not None:
            ok &= torch.isfinite(rows(sh)).all(1)
        assert len(v["checked_rows"]) == len(v["checked_pos_inf_ok"]) <= 6
        for t, inf_ok in zip(v["checked_rows"], v["checked_pos_inf_ok"]):
            t = rows(t)
            ok &= (~(torch.isnan(t) | (t == -torch.inf)) if inf_ok else torch.isfinite(t)).all(1)
        return ~ok

    def backward(self, *args):
        v = self.bind("project_backward_torch", args)
        has_sh = v["sh"].numel() > 0
        leaves = [v[k].detach().clone().requires_grad_(True) for k in ("means3d", "quats", "scales")]
        leaves.append(v["sh"].detach().clone().requires_grad_(True) if has_sh else None)
        with torch.enable_grad():
            out = self._compute(v, leaves)
            assert torch.equal(out["radii"], v["radii"]), "backward got the wrong radii"
            loss = sum((out[k] * v[g]).sum() for k, g in (("means2d", "g_means2d"), ("conics", "g_conics"),
                                                          ("depths", "g_depths")))
            if has_sh:
                loss = loss + (out["colours"] * v["g_colors"]).sum()
        live = [t for t in leaves if t is not None]
        grads = list(torch.autograd.grad(loss, live, allow_unused=True))
        grads = [torch.zeros_like(t) if g is None else g for g, t in zip(grads, live)]
        return grads + ([] if has_sh else [torch.zeros(0)])


class StandInCompositing(_Bound):
    """cuda_v2_binding.cpp's contract through the reference compositing of the rows not culled."""

    def __init__(self):
        super().__init__((CSRC / "cuda_v2_binding.cpp").read_text())

    @staticmethod
    def layout() -> list[int]:
        return LAYOUT

    def _render(self, v, ins):
        keep = torch.ones(v["means2d"].shape[0], dtype=torch.bool) if v["radii"].numel() == 0 else \
            (v["radii"] != 0).any(1)
        pick = lambda t: None if t is None else t[keep]  # noqa: E731
        bg = v["background"] if v["background"].numel() else None
        splats = Splats2D(*(pick(ins[k]) for k in KEYS), background=bg, reg_values=pick(ins["reg_values"]))
        return rasterize_splats_reference(splats, _settings(v))

    def forward(self, *args):
        v = self.bind("forward_v2", args)
        ins = {k: (None if v[k].numel() == 0 else v[k]) for k in
               ("means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma", "reg_values")}
        out = self._render(v, ins)
        self.saved = dict(v=v, ins=ins)
        R = 0 if ins["reg_values"] is None else ins["reg_values"].shape[1]
        outs = dict(rgb=out.rgb, alpha=out.alpha, depth=out.depth,
                    reg=out.reg if R else torch.zeros(v["height"], v["width"], 0),
                    n_contrib=out.stats.n_contrib.int(), T_final=1 - out.alpha,
                    last=torch.full_like(out.alpha, 7).int(), pairs=torch.tensor([12345]),
                    pk=torch.full((v["means2d"].shape[0], 10 + v["colors"].shape[1] + R), 0.5),
                    ranges=torch.zeros(1, 2, dtype=torch.int32), tile_list=torch.arange(3, dtype=torch.int32))
        self.outs = outs
        return [outs[k] for k in returned(self.src, "forward_v2")]

    def backward(self, *args):
        v = self.bind("backward_v2", args)
        for k in ("alpha_out", "depth_out", "T_final", "last", "n_contrib", "pk", "ranges", "tile_list"):
            ref = self.outs[{"alpha_out": "alpha", "depth_out": "depth"}.get(k, k)]
            assert torch.equal(v[k], ref), f"backward got the wrong tensor as {k}"
        assert v["head_budget_bytes"] > 0
        fv, ins = self.saved["v"], self.saved["ins"]
        leaves = {k: (None if t is None else t.detach().clone().requires_grad_(True)) for k, t in ins.items()}
        with torch.enable_grad():
            out = self._render(fv, leaves)
            loss = (out.rgb * v["g_rgb"]).sum() + (out.alpha * v["g_alpha"]).sum() + (out.depth * v["g_depth"]).sum()
            if v["n_reg"]:
                loss = loss + (out.reg * v["g_reg"]).sum()
        live = {k: t for k, t in leaves.items() if t is not None}
        g = dict(zip(live, torch.autograd.grad(loss, list(live.values()), allow_unused=True)))
        n, nch, R = v["n"], v["n_channels"], v["n_reg"]
        packed = torch.zeros(n, 10 + nch + R)
        mx, my, ca, cc, o, d, al, be, ga, col = LAYOUT
        for k, c0, width in (("means2d", mx, 2), ("conics", ca, 3), ("opacities", o, 1), ("depths", d, 1),
                             ("alpha", al, 1), ("beta", be, 1), ("gamma", ga, 1), ("colors", col, nch),
                             ("reg_values", col + nch, R)):
            if g.get(k) is not None:
                packed[:, c0:c0 + width] = g[k].reshape(n, width)
        return [packed]

    # -- the per-pixel entries (cuda_pixel.cu): the CPU backend's re-sorting window ----------------------
    def _render_pixel(self, v, ins):
        from smgs.raster.cpu import rasterize_splats_cpu
        from smgs.raster.types import RayDepth

        assert v["lead_alpha"] in (-1.0, K.LEADER_ALPHA), v["lead_alpha"]
        bg = v["background"] if v["background"].numel() else None
        splats = Splats2D(*(ins[k] for k in KEYS), background=bg, ray_depth=RayDepth(v["coefs"], *v["intr"]))
        return rasterize_splats_cpu(splats, _settings(v, leaders=v["lead_alpha"] >= 0, window=v["window"]))

    def forward_pixel(self, *args):
        v = self.bind("forward_pixel_v2", args)
        ins = {k: (None if v[k].numel() == 0 else v[k]) for k in
               ("means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma")}
        out = self._render_pixel(v, ins)
        self.saved = dict(v=v, ins=ins)
        n, nch = v["means2d"].shape[0], v["colors"].shape[1]
        outs = dict(rgb=out.rgb, alpha=out.alpha, depth=out.depth, n_contrib=out.stats.n_contrib.int(),
                    T_final=1 - out.alpha, pairs=torch.tensor([12345]),
                    leaders=(out.leaders.int() if out.leaders is not None else torch.zeros(0, 0, 2, dtype=torch.int32)),
                    list_end=torch.full_like(out.alpha, 7).int(), pk=torch.full((n, 10 + nch), 0.5),
                    ranges=torch.zeros(1, 2, dtype=torch.int32), tile_list=torch.arange(3, dtype=torch.int32),
                    box=torch.zeros(n, 4, dtype=torch.int32))
        self.outs = outs
        return [outs[k] for k in returned(self.src, "forward_pixel_v2")]

    def backward_pixel(self, *args):
        v = self.bind("backward_pixel_v2", args)
        for k in ("alpha_out", "depth_out", "n_contrib", "pk", "ranges", "tile_list", "box"):
            ref = self.outs[{"alpha_out": "alpha", "depth_out": "depth"}.get(k, k)]
            assert torch.equal(v[k], ref), f"backward_pixel got the wrong tensor as {k}"
        fv, ins = self.saved["v"], self.saved["ins"]
        assert torch.equal(v["coefs"], fv["coefs"]) and v["intr"] == fv["intr"] and v["window"] == fv["window"]
        assert v["scratch_budget_bytes"] > 0
        leaves = {k: (None if t is None else t.detach().clone().requires_grad_(True)) for k, t in ins.items()}
        with torch.enable_grad():
            out = self._render_pixel(fv, leaves)
            loss = (out.rgb * v["g_rgb"]).sum() + (out.alpha * v["g_alpha"]).sum() + (out.depth * v["g_depth"]).sum()
        live = {k: t for k, t in leaves.items() if t is not None}
        g = dict(zip(live, torch.autograd.grad(loss, list(live.values()), allow_unused=True)))
        n, nch = v["n"], v["n_channels"]
        packed = torch.zeros(n, 10 + nch)
        mx, my, ca, cc, o, d, al, be, ga, col = LAYOUT
        for k, c0, width in (("means2d", mx, 2), ("conics", ca, 3), ("opacities", o, 1), ("depths", d, 1),
                             ("alpha", al, 1), ("beta", be, 1), ("gamma", ga, 1), ("colors", col, nch)):
            if g.get(k) is not None:
                packed[:, c0:c0 + width] = g[k].reshape(n, width)
        return [packed]


class OnHost:
    """A stand-in binding above for the stand-in device of tests/device_mix.py (Remote tensors):
    computes on their host values with the dispatch mode off (that is the GPU's own work), returns
    its outputs on the stand-in device, and counts its calls (``mode.bindings``) and the real
    binding's synchronisations: ``forward_sync`` after each forward, ``softmax_backward_sync``
    before a softmax backward."""

    def __init__(self, base, mode, forward_sync: str | None = None, softmax_backward_sync: str | None = None):
        self.base, self.mode = base, mode
        self.forward_sync, self.softmax_backward_sync = forward_sync, softmax_backward_sync

    def _on_host(self, fn, args):
        from device_mix import Remote
        from torch.utils._python_dispatch import _disable_current_modes

        host = lambda a: a.inner if type(a) is Remote else [host(b) for b in a] if isinstance(a, list) else a  # noqa: E731
        with _disable_current_modes():
            out = fn(*[host(a) for a in args])
        return [Remote(t) for t in out]

    def layout(self) -> list[int]:
        return self.base.layout()

    def forward(self, *args):
        self.mode.bindings[type(self.base).__name__ + " forward"] += 1
        out = self._on_host(self.base.forward, args)
        if self.forward_sync:
            self.mode.sync(self.forward_sync)
        return out

    def backward(self, *args):
        self.mode.bindings[type(self.base).__name__ + " backward"] += 1
        if self.softmax_backward_sync and dict(zip([n for _, n in params(self.base.src, "backward_v2")],
                                                   args))["use_softmax"]:
            self.mode.sync(self.softmax_backward_sync)
        return self._on_host(self.base.backward, args)
