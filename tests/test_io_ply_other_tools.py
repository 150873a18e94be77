"""PLYs of other tools: Mip-Splatting's 3D filter is folded in as its own fused export does, a property
smgs cannot render (a 4D or spacetime model's time and motion) is refused naming it instead of being
dropped, and a model of no Gaussians is not scored."""

from __future__ import annotations

import numpy as np
import pytest

from protocols import evaluate_ply
from smgs.data import load_scene
from smgs.io.ply import FILTER_3D_NOTE, PlyFormatError, read_ply
from test_io_ply import known_gaussians, write_by_hand


@pytest.fixture(scope="module")
def scene():
    return load_scene("procedural", n_views=8, width=48, height=32, test_every=4)


def _sigmoid(x):
    return 1 / (1 + np.exp(-x.astype(np.float64)))


def test_mip_splattings_3d_filter_is_folded_into_scale_and_opacity(scene, tmp_path):
    k = known_gaussians(scene, 40, 1)
    f = np.random.default_rng(1).uniform(0.0, 0.05, 40).astype(np.float32) * scene.extent
    write_by_hand(tmp_path / "mip.ply", **k, extras={"filter_3D": f})
    s = read_ply(tmp_path / "mip.ply")
    # Mip-Splatting (Yu et al. 2024, its get_scaling_with_3D_filter / get_opacity_with_3D_filter):
    # the filtered Gaussian has variances s² + f² per axis and its opacity scaled by the ratio of the
    # covariance determinants' square roots
    s2 = np.exp(2 * k["log_scales"].astype(np.float64))
    s2f = s2 + f.astype(np.float64)[:, None] ** 2
    np.testing.assert_allclose(np.exp(s.scales.astype(np.float64)), np.sqrt(s2f), rtol=1e-6)
    expect = _sigmoid(k["opacity_logit"]) * np.sqrt(s2.prod(1) / s2f.prod(1))
    np.testing.assert_allclose(_sigmoid(s.opacities), expect, rtol=1e-5)
    assert s.meta["filter_3D"] == FILTER_3D_NOTE and "ignored" not in s.meta
    np.testing.assert_array_equal(s.means, k["means"])   # nothing else changes
    # a zero filter leaves the file's Gaussians as they are
    write_by_hand(tmp_path / "zero.ply", **k, extras={"filter_3D": np.zeros(40, np.float32)})
    z = read_ply(tmp_path / "zero.ply")
    np.testing.assert_allclose(z.scales, k["log_scales"], rtol=0, atol=1e-6)
    np.testing.assert_allclose(z.opacities, k["opacity_logit"], rtol=0, atol=1e-5)


def test_a_negative_3d_filter_is_refused(scene, tmp_path):
    k = known_gaussians(scene, 10, 0)
    f = np.full(10, 0.01, np.float32)
    f[3] = -0.5
    write_by_hand(tmp_path / "m.ply", **k, extras={"filter_3D": f})
    with pytest.raises(PlyFormatError, match=r"filter_3D has 1 negative value\(s\) \(vertex 3: -0.5\)"):
        read_ply(tmp_path / "m.ply")


@pytest.mark.parametrize("extras", [["t", "motion_0", "motion_1", "omega_0"], ["trbf_center", "trbf_scale"]])
def test_properties_that_change_rendering_are_refused_by_name(scene, tmp_path, extras):
    k = known_gaussians(scene, 10, 0)
    write_by_hand(tmp_path / "4d.ply", **k, extras={e: np.ones(10, np.float32) for e in extras})
    with pytest.raises(PlyFormatError) as e:
        read_ply(tmp_path / "4d.ply")
    assert f"properties smgs cannot render: {' '.join(extras)}" in str(e.value)
    assert "4D or spacetime" in str(e.value) and str(tmp_path / "4d.ply") in str(e.value)


def test_preview_colours_do_not_change_rendering_and_are_read_past(scene, tmp_path):
    k = known_gaussians(scene, 10, 0)
    write_by_hand(tmp_path / "c.ply", **k, extras={c: np.ones(10, np.float32) for c in ("red", "green", "blue")})
    assert read_ply(tmp_path / "c.ply").meta["ignored"] == "red green blue"


def test_a_model_of_no_gaussians_is_not_scored_and_a_name_with_equals_is_the_file(scene, tmp_path, capsys):
    k = {key: v[:0] for key, v in known_gaussians(scene, 10, 0).items()}
    ply = tmp_path / "iter=30000.ply"
    write_by_hand(ply, **k)
    assert len(read_ply(ply)) == 0    # a collapsed run's export still reads back as written
    out = tmp_path / "out"
    # refused before anything runs: exit status 2 (docs/usage.md, "Exit status")
    assert evaluate_ply.main([str(ply), f"out_dir={out}", "dataset.width=32", "dataset.height=24"]) == 2
    err = capsys.readouterr().err
    assert f"error: {ply}: 0 vertices: a model of no Gaussians, nothing to score" in err and "Traceback" not in err
    assert not out.exists()
