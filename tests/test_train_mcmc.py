"""The MCMC densification strategy: the relocation formula against renders, the cap, the noise
gate, Adam moments of moved Gaussians, resume from a checkpoint, and the configs that pick it."""

import io

import pytest
import torch

from smgs.camera import Camera
from smgs.data.patterns import pattern_scene
from smgs.raster import rasterize
from smgs.raster.projection import quat_to_rotmat
from smgs.train import GaussianConfig, Gaussians, TrainConfig, densify_config, from_dict, pattern_config, to_dict
from smgs.train.strategies.mcmc import MCMCStrategy, noise_gate, position_noise, relocation
from smgs.train.optim import GaussianOptimizer
from smgs.train.strategies import DefaultStrategy, StrategyRun, start_strategy
from smgs.train.trainer import Trainer

F64 = torch.float64
RUN = StrategyRun(1.0, "3dgs", 0, torch.device("cpu"))


# -- the relocation formula ------------------------------------------------------------------

def test_relocation_identities():
    o = torch.tensor([0.01, 0.3, 0.7, 0.99], dtype=F64)
    s = torch.rand(4, 3, dtype=F64) + 0.1
    o1, s1 = relocation(o, s, torch.ones(4))
    torch.testing.assert_close(o1, o)                  # N = 1: nothing changes
    torch.testing.assert_close(s1, s)
    for n in (2, 3, 7, 51):
        on, sn = relocation(o, s, torch.full((4,), n))
        # N composited copies have the source's opacity at the centre
        torch.testing.assert_close(1 - (1 - on) ** n, o)
        # scales shrink, by the same factor on every axis, less the fainter the source
        ratio = sn / s
        torch.testing.assert_close(ratio, ratio[:, :1].expand(4, 3))
        assert (ratio < 1).all() and (ratio[:-1, 0] > ratio[1:, 0]).all()
    # faint limit: N copies of o/N, same size (first order in o)
    on, sn = relocation(torch.tensor([1e-6], dtype=F64), torch.ones(1, 3, dtype=F64), torch.tensor([4]))
    torch.testing.assert_close(on * 4, torch.tensor([1e-6], dtype=F64), rtol=1e-5, atol=0)
    torch.testing.assert_close(sn, torch.ones(1, 3, dtype=F64), rtol=1e-5, atol=0)


CAM = Camera(torch.tensor([[64.0, 0, 32], [0, 64.0, 32], [0, 0, 1]], dtype=F64), torch.eye(4, dtype=F64), 64, 64)


def _alpha(opacity: float, scale: torch.Tensor, n: int) -> torch.Tensor:
    """Alpha of n identical splats at one place (reference renderer, float64)."""
    return rasterize(torch.tensor([[0.0, 0.0, 2.0]], dtype=F64).repeat(n, 1),
                     torch.tensor([[1.0, 0, 0, 0]], dtype=F64).repeat(n, 1), scale.reshape(1, 3).repeat(n, 1),
                     torch.full((n,), opacity, dtype=F64), torch.ones(n, 3, dtype=F64), CAM, mode="3dgs",
                     backend="reference").alpha


@pytest.mark.parametrize("n", [2, 3, 5])
def test_relocation_keeps_the_render_to_first_order(n):
    """A splat (σ ≈ 8 px) rendered alone, then as its n relocated copies: the difference is
    second order in the opacity (relative error ∝ o), where naive copies are off by ~(n − 1)·o.
    Compared where one copy passes the renderer's 1/255 skip (outside it the faint copies are
    dropped by the renderer's convention, not by the formula)."""
    scale = torch.full((3,), 0.25, dtype=F64)
    errs = []
    for o in (0.2, 0.1):
        before = _alpha(o, scale, 1)
        on, sn = relocation(torch.tensor([o], dtype=F64), scale[None], torch.tensor([n]))
        after = _alpha(float(on), sn[0], n)
        naive = _alpha(o, scale, n)
        inside = _alpha(float(on), sn[0], 1) >= 2 / 255
        assert inside.sum() > 300
        err = float(((after - before).abs() * inside).sum() / (before * inside).sum())
        err_naive = float(((naive - before).abs() * inside).sum() / (before * inside).sum())
        assert err < 0.06 * o, (o, err)
        assert err_naive > 0.5 * (n - 1)
        errs.append(err)
    assert errs[1] < 0.6 * errs[0]        # halving o at least halves the relative error: first order kept


# -- a strategy on hand-made Gaussians -------------------------------------------------------

def _gaussians(opacities: list[float]) -> tuple[Gaussians, GaussianOptimizer]:
    n = len(opacities)
    gen = torch.Generator().manual_seed(3)
    g = Gaussians.from_points(torch.randn(n, 3, generator=gen), torch.rand(n, 3, generator=gen), GaussianConfig(),
                              1.0, 0, scales=torch.full((n, 3), 0.1), device="cpu")
    with torch.no_grad():
        g.params["opacities"].copy_(torch.logit(torch.tensor(opacities)))
    opt = GaussianOptimizer(g, TrainConfig().optim, 1.0, 100)
    return g, opt


def _mcmc(**over) -> MCMCStrategy:
    return densify_config("mcmc", **{"cap": 100, "refine_start": 0, "refine_every": 1, **over}).start(RUN)


def test_relocation_moves_dead_onto_live_and_resets_their_adam_moments():
    g, opt = _gaussians([0.001, 0.8, 0.002, 0.6, 0.3])
    for p in g.params.values():           # one optimiser step so that every moment is non-zero
        p.grad = torch.ones_like(p)
    opt.step()
    before = {k: v.detach().clone() for k, v in g.params.items()}
    st = _mcmc()
    assert st.relocate(g, opt) == 2
    live = [1, 3, 4]
    for d in (0, 2):                      # each dead one is now a copy of a live one
        src = [i for i in live if torch.equal(g.params["means"][d], before["means"][i])]
        assert len(src) == 1
        for k in g.params:
            torch.testing.assert_close(g.params[k][d], g.params[k][src[0]])
    changed = (g.opacities.detach() != torch.sigmoid(before["opacities"])).nonzero().squeeze(1).tolist()
    sources = [i for i in live if i in changed]
    assert sources and set(changed) == {0, 2, *sources}
    for name in opt.names:                # moments zero exactly on the changed rows
        if g.params[name].numel() == 0:
            continue
        s = opt.opt.state[g.params[name]]
        for k in ("exp_avg", "exp_avg_sq"):
            zero = (s[k].reshape(len(g), -1) == 0).all(1)
            assert zero.nonzero().squeeze(1).tolist() == sorted(changed), (name, k)
    assert (g.opacities > 0.005).all()


def test_growth_stops_at_the_cap():
    g, opt = _gaussians([0.5] * 10)
    st = _mcmc(cap=13, mcmc_grow_rate=0.05)
    added = [st.grow(g, opt) for _ in range(5)]
    assert added == [1, 1, 1, 0, 0] and len(g) == 13       # at least one per step, never past the cap
    assert all(len(opt.opt.state[g.params[n]]["exp_avg"]) == 13 for n in opt.names if opt.opt.state.get(g.params[n]))


def test_noise_vanishes_for_opaque_gaussians():
    g, opt = _gaussians([0.999, 0.9, 0.5, 0.001])
    gate = noise_gate(g.opacities.detach(), 100.0, 0.005)
    assert float(gate[0]) < 1e-40 and float(gate[3]) > 0.5
    noise = position_noise(g, lr_means=1.6e-4, noise_lr=5e5, k=100.0, t=0.005,
                           generator=torch.Generator().manual_seed(0))
    norms = noise.norm(dim=1)
    assert float(norms[0]) == 0 and float(norms[1]) == 0 and float(norms[2]) == 0 and float(norms[3]) > 1e-5
    st = _mcmc(refine_every=1000)           # a step without refinement: only the noise moves means
    before = g.means.detach().clone()
    st.step_post_backward(1, g, opt, None, None, lr_means=1.6e-4)
    assert torch.equal(g.means[:3], before[:3]) and not torch.equal(g.means[3], before[3])


def test_noise_is_the_covariance_times_a_normal_sample():
    g, _ = _gaussians([0.001, 0.01, 0.02, 0.05])
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        g.params["quats"].copy_(torch.randn(4, 4, generator=gen))
        g.params["scales"].copy_(torch.randn(4, 3, generator=gen).mul(0.5).add(-1.0))
    got = position_noise(g, 1e-4, 5e5, 100.0, 0.005, torch.Generator().manual_seed(2))
    eps = torch.randn((4, 3), generator=torch.Generator().manual_seed(2))
    rot, s = quat_to_rotmat(g.quats.detach()), torch.diag_embed(g.scales.detach())
    cov = rot @ s @ s @ rot.transpose(1, 2)
    gate = torch.sigmoid(-100.0 * (g.opacities.detach() - 0.005))
    torch.testing.assert_close(got, (cov @ eps[:, :, None]).squeeze(-1) * (gate * 5e5 * 1e-4)[:, None])


# -- in training -----------------------------------------------------------------------------

def _trainer(cap: int = 12, steps: int = 60, mode: str = "3dgs") -> Trainer:
    cfg = to_dict(pattern_config(mode, cap=cap, steps=steps))
    cfg["densify"] = {"budget_kind": "mcmc", "cap": cap, "refine_start": 2, "refine_every": 3, "refine_stop": steps}
    return Trainer(pattern_scene("circle4", 16), from_dict(TrainConfig, cfg), device="cpu")


def test_count_never_exceeds_the_cap():
    tr = _trainer(cap=12, steps=60)
    assert isinstance(tr.strategy, MCMCStrategy)
    counts = [int(tr.train_step(i)["num_gaussians"]) for i in range(60)]
    assert max(counts) == 12 and counts[0] == 4 and all(a <= b for a, b in zip(counts, counts[1:]))
    # more initial Gaussians than the cap: a random subset of cap of them is kept
    cfg = to_dict(pattern_config("3dgs", cap=3, steps=10))
    cfg["densify"] = {"budget_kind": "mcmc", "cap": 3}
    tr = Trainer(pattern_scene("circle4", 16), from_dict(TrainConfig, cfg), device="cpu")
    assert len(tr.gaussians) == 3 and any("above the cap 3" in p for p in tr.plan)


def test_loss_has_the_l1_regularisers():
    tr = _trainer()
    g = tr.gaussians
    c = tr.cfg.densify
    expected = c.mcmc_opacity_reg * g.opacities.mean() + c.mcmc_scale_reg * g.scales.mean()
    torch.testing.assert_close(tr.strategy.regularizer(1, g), expected)
    off = densify_config("mcmc", cap=4, mcmc_opacity_reg=0.0, mcmc_scale_reg=0.0).start(RUN)
    assert off.regularizer(1, g) is None


def _state(tr: Trainer) -> dict:
    return {"g": tr.gaussians.state_dict(), "opt": tr.optimizer.state_dict(), "st": tr.strategy.state_dict()}


def test_resume_mid_run_matches_an_uninterrupted_run():
    steps, cut = 30, 13                       # the cut falls between refinements
    full = _trainer(cap=10, steps=steps, mode="softmax_gs")
    for i in range(steps):
        full.train_step(i)
    first = _trainer(cap=10, steps=steps, mode="softmax_gs")
    for i in range(cut):
        first.train_step(i)
    buf = io.BytesIO()
    torch.save(first.state_dict(), buf)
    buf.seek(0)
    resumed = _trainer(cap=10, steps=steps, mode="softmax_gs")
    resumed.load_state_dict(torch.load(buf, weights_only=False))
    for i in range(cut, steps):
        resumed.train_step(i)
    a, b = _state(full), _state(resumed)
    assert len(full.gaussians) == len(resumed.gaussians) > 4
    for k in a["g"]:
        assert torch.equal(a["g"][k], b["g"][k]), k
    for name, st in a["opt"]["groups"].items():
        for k in ("exp_avg", "exp_avg_sq"):
            assert torch.equal(st[k], b["opt"]["groups"][name][k]), (name, k)
    assert torch.equal(a["st"]["gen"]["state"], b["st"]["gen"]["state"])


def test_checkpoint_of_another_strategy_is_refused():
    tr = _trainer()
    default = densify_config("full").start(RUN)
    with pytest.raises(ValueError, match="'default'.*this run uses 'mcmc'"):
        tr.strategy.load_state_dict(default.state_dict())
    with pytest.raises(ValueError, match="'mcmc'.*this run uses 'default'"):
        default.load_state_dict(tr.strategy.state_dict())


# -- configs ---------------------------------------------------------------------------------

def test_configs_pick_the_strategy():
    assert isinstance(start_strategy(densify_config("full"), RUN), DefaultStrategy)
    st = start_strategy(densify_config("mcmc", cap=50), RUN)
    assert isinstance(st, MCMCStrategy) and st.reset_every is None and st.refine_stop == 25_000
    with pytest.raises(ValueError, match="budget 'mcmc' needs cap"):
        densify_config("mcmc")
    with pytest.raises(ValueError, match="unknown densification strategy 'gsplat'"):
        densify_config("full", strategy="gsplat")


def test_mcmc_budget_yaml_reaches_the_trainer_with_its_schedule_scaled():
    pytest.importorskip("hydra")
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from baselines.trainer_settings import train_config
    from protocols.method_defaults import register
    from protocols.run_settings import method_settings, run_settings
    from pathlib import Path

    register()   # the method configs take the trainer's defaults from Hydra's store, as protocols.run does
    root = Path(__file__).resolve().parents[1] / "configs"
    with initialize_config_dir(config_dir=str(root), version_base=None):
        cfg = compose(config_name="config", overrides=["budget=mcmc_2593000", "method=softmax_gs",
                                                        "dataset=procedural", "protocol=cpu"])
    cell = OmegaConf.to_container(cfg, resolve=True)
    mc = train_config(method_settings(cell), run_settings(cell))
    d = from_dict(TrainConfig, mc).densify
    assert d.strategy == "mcmc" and d.cap == 2_593_000 and d.reset_every is None
    assert (d.refine_start, d.refine_stop, d.refine_every) == (50, 2500, 10)   # 500/25000/100 × 3000/30000


def test_report_maps_mcmc_budgets_to_the_papers_rows():
    from reports.paper import budget_group, load_paper, paper_key, row_label

    p = load_paper()
    assert paper_key("3dgs", "mcmc_2593000") == "gs_mcmc" and paper_key("softmax_gs", "mcmc_4") == "softmax_gs_mcmc"
    assert paper_key("gef_only", "mcmc_2593000") is None and budget_group("mcmc_1900000") == "dense"
    assert p.t2("softmax_gs", "mcmc_2593000", "mipnerf360", "psnr") == 29.73
    assert p.t2("3dgs", "mcmc_1900000", "tandt", "lpips") == 0.189
    assert p.t2("3dgs", "mcmc_2593000", "tandt", "psnr") is None       # the paper's tandt row has another cap
    assert row_label("3dgs", "mcmc_2593000") == "3D GS-MCMC (cap 2,593,000)"
