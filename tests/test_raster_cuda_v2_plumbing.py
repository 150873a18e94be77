"""The opt-in CUDA kernels' Python side (smgs.raster.cuda_v2, smgs.raster.projection_cuda), without
a GPU: the switch, and the argument plumbing between the autograd Functions and the torch bindings.

Stand-in extensions take their parameter names, types and order from the bindings' C++ sources
(projection_cuda_binding.cpp, cuda_v2_binding.cpp: the signatures and their py::arg names) and their
output order from the documented return lists, and compute with the PyTorch oracles (``_Project``,
``eval_sh``, the reference compositing) on CPU tensors, keeping the bindings' contracts: no
compaction (culled rows zeros with radii (0, 0)), rows with radii (0, 0) never composited, the
backward's packed [N, S] gradient. Through them, ``rasterize_fused`` must give the reference
backend's images and gradients of every 3D input. A swapped argument, a misplaced saved tensor, a
misrouted gradient or a culled row that leaks into the image fails here.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from smgs.camera import Camera
from smgs.raster import constants as K
from smgs.raster import cuda_v2, rasterize
from smgs.raster.projection import _Project, _View
from smgs.raster.reference import rasterize_splats_reference
from smgs.raster.sh import eval_sh
from smgs.raster.types import MODES

CSRC = Path(cuda_v2.__file__).parent / "csrc"
PYTYPE = {"at::Tensor": torch.Tensor, "int64_t": int, "bool": bool, "double": float, "std::vector<double>": list}
LAYOUT = [0, 1, 2, 4, 5, 6, 7, 8, 9, 10]   # cuda_kernel.h's P_* (checked against the enum below)


def _params(src: str, fn: str) -> list[tuple[str, str]]:
    m = re.search(rf"std::vector<at::Tensor> {fn}\((.*?)\)\s*\{{", src, re.S)
    assert m, fn
    return [tuple(" ".join(p.split()).rsplit(" ", 1)) for p in m.group(1).split(",")]


def _py_args(src: str, name: str) -> list[str]:
    m = re.search(rf'm\.def\("{name}",(.*?)\);', src, re.S)
    assert m, name
    return re.findall(r'py::arg\("(\w+)"\)', m.group(1))


def _returned(src: str, fn: str) -> list[str]:
    m = re.search(rf"// Returns \[([^\n]*)\]\.?\n(?://[^\n]*\n)*std::vector<at::Tensor> {fn}\(", src)
    assert m, fn
    return [re.sub(r"\s*\[.*|\s*\(.*", "", s).strip() for s in re.split(r",\s*(?![^\[]*\])", m.group(1))]


class _Bound:
    def __init__(self, src: str):
        self.src, self.calls = src, []

    def bind(self, fn: str, args) -> dict:
        params = _params(self.src, fn)
        assert len(args) == len(params), f"{fn}: {len(args)} arguments for {len(params)} parameters"
        for (t, n), a in zip(params, args):
            want = PYTYPE[t]
            assert isinstance(a, want) and (want is not int or not isinstance(a, bool)), \
                f"{fn}: parameter {n} ({t}) got {type(a).__name__}"
        self.calls.append(fn)
        return {n: a for (_, n), a in zip(params, args)}


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
        return [out[k] for k in _returned(self.src, "project_forward_torch")]

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
        mode = {(False, False): "3dgs", (True, False): "gef_only", (False, True): "softmax_only",
                (True, True): "softmax_gs"}[(v["use_gef"], v["use_softmax"])]
        bg = v["background"] if v["background"].numel() else None
        return rasterize_splats_reference(
            *(pick(ins[k]) for k in ("means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma")),
            v["width"], v["height"], mode=mode, k_max=v["k_max"], background=bg,
            eq15="solved" if v["solved"] else "printed", reg_values=pick(ins["reg_values"]),
            reg_depth_scale=v["reg_scale"], k_max_scope="patch" if v["patch"] else "pixel")

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
        return [outs[k] for k in _returned(self.src, "forward_v2")]

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


def _scene(n: int, seed: int, sh_degree: int | None):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    means = (r(n, 3) - 0.5) * torch.tensor([2.0, 1.6, 1.0]) + torch.tensor([0.0, 0.0, 3.0])
    means[:3, 2] = -3.0                               # behind the camera (at z = -2)
    means[3:5, 0] = 40.0                              # far off the image
    quats = torch.randn(n, 4, generator=g)
    scales = 0.05 + 0.1 * r(n, 3)
    colors = r(n, 9, 3) - 0.5 if sh_degree is not None else r(n, 3)
    return dict(means3d=means, quats=quats, scales=scales, opacities=0.3 + 0.6 * r(n), colors_or_sh=colors,
                alpha=0.5 + 2 * r(n), beta=8 * r(n), gamma=2 * r(n))


def _render(sc, cam, mode, via_fused: bool, sh_degree, **kw):
    leaves = {k: t.clone().requires_grad_(True) for k, t in sc.items()}
    common = dict(mode=mode, k_max=4, sh_degree=sh_degree, background=None, eq15="solved", reg_values=None,
                  reg_depth_scale=1.0, near_plane=K.NEAR_PLANE, eps2d=K.EPS2D, clamp_sh_colors=True, t_min=K.T_MIN,
                  **kw)
    if via_fused:
        exts = (StandInProjection(), StandInCompositing())
        out = cuda_v2.rasterize_fused(leaves["means3d"], leaves["quats"], leaves["scales"], leaves["opacities"],
                                      leaves["colors_or_sh"], cam, leaves["alpha"], leaves["beta"], leaves["gamma"],
                                      exts=exts, **common)
    else:
        exts = ()
        common.pop("clamp_sh_colors")
        out = rasterize(leaves["means3d"], leaves["quats"], leaves["scales"], leaves["opacities"],
                        leaves["colors_or_sh"], cam, leaves["alpha"], leaves["beta"], leaves["gamma"],
                        backend="reference", **common)
    g = torch.Generator().manual_seed(3)
    loss = sum((t * torch.rand(t.shape, generator=g)).sum() for t in (out.rgb, out.alpha, out.depth))
    loss.backward()
    return out, {k: t.grad for k, t in leaves.items()}, exts


@pytest.mark.parametrize("mode,sh_degree,scope", [(m, None, "pixel") for m in MODES]
                         + [(m, 2, "pixel") for m in MODES] + [("softmax_gs", 2, "patch")])
def test_fused_plumbing_matches_the_reference(mode, sh_degree, scope):
    cam = Camera.look_at([0.1, -0.1, -2.0], [0.0, 0.0, 3.0], [0, -1, 0], fx=40.0, fy=38.0, width=23, height=19)
    sc = _scene(40, 1, sh_degree)
    of, gf, exts = _render(sc, cam, mode, True, sh_degree, k_max_scope=scope)
    orf, gr, _ = _render(sc, cam, mode, False, sh_degree, k_max_scope=scope)
    assert of.stats.scope == scope
    assert exts[0].calls == ["project_forward_torch", "project_backward_torch"]
    assert exts[1].calls == ["forward_v2", "backward_v2"]
    for a, b in ((of.rgb, orf.rgb), (of.alpha, orf.alpha), (of.depth, orf.depth)):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6)
    assert torch.equal(of.stats.n_contrib, orf.stats.n_contrib) and of.stats.pairs_evaluated == 12345
    n = sc["means3d"].shape[0]
    assert torch.equal(of.extras["ids"], torch.arange(n))
    culled = torch.ones(n, dtype=torch.bool)
    culled[orf.extras["ids"]] = False
    assert culled[:5].all() and (of.extras["radii"][culled] == 0).all()
    assert torch.equal(of.extras["radii"][~culled], orf.extras["radii"])
    for k, want in gr.items():
        got = gf[k]
        if want is None:
            assert got is None or (got == 0).all(), k
            continue
        scale = want.abs().max().clamp_min(1e-12)
        torch.testing.assert_close(got / scale, want / scale, rtol=0, atol=1e-5, msg=k)


def test_layout_matches_the_kernel_header():
    body = re.search(r"enum \{([^}]*)\}", (CSRC / "cuda_kernel.h").read_text()).group(1)
    P = {s.split("=")[0].strip(): i for i, s in enumerate(body.split(","))}
    assert LAYOUT == [P[k] for k in ("P_MX", "P_MY", "P_CA", "P_CC", "P_O", "P_D", "P_AL", "P_BE", "P_GA", "P_COL")]
    layout = re.search(r'm\.def\("layout", \[\]\(\) \{ return std::vector<int>\{([^}]*)\}', (CSRC / "cuda_v2_binding.cpp")
                       .read_text()).group(1)
    assert [s.strip() for s in layout.split(",")] == ["P_MX", "P_MY", "P_CA", "P_CC", "P_O", "P_D", "P_AL", "P_BE",
                                                      "P_GA", "P_COL"]


def test_bindings_signatures_and_pybind_names_agree():
    for src, pairs in (((CSRC / "projection_cuda_binding.cpp").read_text(),
                        (("project_forward_torch", "forward"), ("project_backward_torch", "backward"))),
                       ((CSRC / "cuda_v2_binding.cpp").read_text(), (("forward_v2", "forward"),
                                                                      ("backward_v2", "backward")))):
        for fn, name in pairs:
            params = _params(src, fn)
            assert [n for _, n in params] == _py_args(src, name), fn
            assert all(t in PYTYPE for t, _ in params), params
    v2 = (CSRC / "cuda_v2_binding.cpp").read_text()
    assert len(_returned(v2, "forward_v2")) == 11
    assert len(_returned((CSRC / "projection_cuda_binding.cpp").read_text(), "project_forward_torch")) == 5


def test_kernel_choice_reads_the_argument_then_the_environment(monkeypatch):
    monkeypatch.delenv(cuda_v2.KERNELS_ENV, raising=False)
    assert cuda_v2.kernel_choice(None) == "default"
    assert cuda_v2.kernel_choice("v2") == "v2"
    monkeypatch.setenv(cuda_v2.KERNELS_ENV, "v2")
    assert cuda_v2.kernel_choice(None) == "v2" and cuda_v2.kernel_choice("default") == "default"
    monkeypatch.setenv(cuda_v2.KERNELS_ENV, "v3")
    with pytest.raises(ValueError, match="SMGS_CUDA_KERNELS='v3'.*default, v2"):
        cuda_v2.kernel_choice(None)
    with pytest.raises(ValueError, match="cuda_kernels='fast'"):
        cuda_v2.kernel_choice("fast")


def test_v2_applies_only_where_the_cuda_backend_renders(monkeypatch):
    """On CPU tensors the choice changes nothing (the cpu/reference backends render)."""
    cam = Camera.look_at([0.1, -0.1, -2.0], [0.0, 0.0, 3.0], [0, -1, 0], fx=40.0, fy=38.0, width=23, height=19)
    sc = _scene(20, 2, None)
    kw = dict(mode="3dgs", backend="reference")
    a = rasterize(sc["means3d"], sc["quats"], sc["scales"], sc["opacities"], sc["colors_or_sh"], cam, **kw)
    b = rasterize(sc["means3d"], sc["quats"], sc["scales"], sc["opacities"], sc["colors_or_sh"], cam,
                  cuda_kernels="v2", **kw)
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.extras["ids"], b.extras["ids"])
