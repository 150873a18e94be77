"""The 3DGS PLY (smgs.io.ply): conventions against a minimal independent writer, round trips of
every method, and a clear error for each kind of bad file."""

from __future__ import annotations

import math
import os

import numpy as np
import plyfile
import pytest
import torch

from baselines.registry import create_method
from baselines.splatting import GaussianSplatting
from smgs.data import load_scene
from smgs.io.ply import PlyFormatError, read_ply, write_ply
from smgs.raster import rasterize

METHODS = ["3dgs", "gef_only", "softmax_only", "softmax_gs"]


@pytest.fixture(scope="module")
def scene():
    return load_scene("procedural", n_views=8, width=48, height=32, test_every=4)


# ---- a minimal writer of the original layout, independent of smgs.io.ply ----------------------

def write_by_hand(path, means, sh, opacity_logit, log_scales, quats, extras=None, fmt="binary_little_endian"):
    """3DGS save_ply spelled out: x y z nx ny nz f_dc_0..2 f_rest_* (f_rest_{c*(K-1)+j} = coefficient
    j+1 of channel c) opacity scale_0..2 rot_0..3, float32, header by hand."""
    n, k = sh.shape[:2]
    extras = extras or {}
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(3 * (k - 1))]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"] + list(extras))
    order = ">" if fmt == "binary_big_endian" else "<"
    arr = np.zeros(n, dtype=[(name, f"{order}f4") for name in names])
    for i, a in enumerate("xyz"):
        arr[a] = means[:, i]
    for c in range(3):
        arr[f"f_dc_{c}"] = sh[:, 0, c]
        for j in range(k - 1):
            arr[f"f_rest_{c * (k - 1) + j}"] = sh[:, 1 + j, c]
    arr["opacity"] = opacity_logit
    for i in range(3):
        arr[f"scale_{i}"] = log_scales[:, i]
    for i in range(4):
        arr[f"rot_{i}"] = quats[:, i]
    for name, v in extras.items():
        arr[name] = v
    header = (f"ply\nformat {fmt} 1.0\nelement vertex {n}\n" + "".join(f"property float {x}\n" for x in names)
              + "end_header\n")
    body = "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in arr.tolist()).encode() \
        if fmt == "ascii" else arr.tobytes()
    with open(path, "wb") as f:
        f.write(header.encode() + body)


def known_gaussians(scene, n, degree, seed=0):
    g = np.random.default_rng(seed)
    pts = scene.points[torch.randperm(scene.points.shape[0], generator=torch.Generator().manual_seed(seed))[:n]]
    return dict(means=pts.numpy().astype(np.float32),
                sh=(g.normal(size=(n, (degree + 1) ** 2, 3)) * 0.4).astype(np.float32),
                opacity_logit=g.normal(size=n).astype(np.float32),
                log_scales=np.log(g.uniform(0.02, 0.12, size=(n, 3)) * scene.extent / 4).astype(np.float32),
                quats=g.normal(size=(n, 4)).astype(np.float32))


def _t(a):
    return torch.from_numpy(np.asarray(a, dtype=np.float32))


@pytest.mark.parametrize("degree", [0, 3])
def test_hand_written_file_renders_as_the_gaussians_passed_to_rasterize(scene, tmp_path, degree):
    k = known_gaussians(scene, 400, degree)
    write_by_hand(tmp_path / "m.ply", **k)
    s = read_ply(tmp_path / "m.ply")
    assert s.sh_degree == degree and s.mode == "3dgs" and len(s) == 400
    np.testing.assert_array_equal(s.sh, k["sh"])   # channel-major f_rest read back in place
    model = GaussianSplatting.from_ply(scene, tmp_path / "m.ply", device="cpu")
    assert model.name == "3dgs"
    for v in scene.test:
        want = rasterize(_t(k["means"]), _t(k["quats"]), torch.exp(_t(k["log_scales"])),
                         torch.sigmoid(_t(k["opacity_logit"])), _t(k["sh"]), v.camera, mode="3dgs",
                         sh_degree=degree, background=scene.background)
        got = model.render(v.camera)
        assert want.rgb.std() > 0.01          # the Gaussians are in view
        assert float((got.rgb - want.rgb).abs().max()) <= 1e-6
        assert float((got.alpha - want.alpha).abs().max()) <= 1e-6


def test_hand_written_extras_are_raw_values_under_exp_and_the_scene_extent(scene, tmp_path):
    k = known_gaussians(scene, 300, 1, seed=1)
    g = np.random.default_rng(2)
    raw = {name: g.normal(scale=0.5, size=300).astype(np.float32)
           for name in ("gef_alpha", "softmax_beta", "softmax_gamma")}
    raw["softmax_beta"] += math.log(20.0)
    write_by_hand(tmp_path / "m.ply", **k, extras=raw)
    model = GaussianSplatting.from_ply(scene, tmp_path / "m.ply", device="cpu")
    assert model.name == "softmax_gs"
    for v in scene.test:
        want = rasterize(_t(k["means"]), _t(k["quats"]), torch.exp(_t(k["log_scales"])),
                         torch.sigmoid(_t(k["opacity_logit"])), _t(k["sh"]), v.camera,
                         alpha=torch.exp(_t(raw["gef_alpha"])), beta=torch.exp(_t(raw["softmax_beta"])),
                         gamma=torch.exp(_t(raw["softmax_gamma"])) / scene.extent, mode="softmax_gs",
                         sh_degree=1, background=scene.background)
        assert float((model.render(v.camera).rgb - want.rgb).abs().max()) <= 1e-6


@pytest.mark.parametrize("method", METHODS)
def test_train_export_import_renders_the_same(scene, tmp_path, method):
    cfg = {"steps": 8, "sh_degree_interval": 3, "densify": {"enabled": False},
           "optim": {"alpha_lr": 1e-2, "beta_lr": 1e-2, "gamma_lr": 1e-2, "shN_lr": 1e-2}}
    m = create_method(method, scene, cfg, device="cpu")
    for step in range(8):
        m.train_step(step)
    path = m.export_ply(tmp_path / "model.ply")
    s = read_ply(path)
    assert s.mode == method and s.sh_degree == 2 == m.trainer.sh_degree()
    assert s.meta["mode"] == method and s.meta["step"] == "8"
    back = GaussianSplatting.from_ply(scene, path, device="cpu")
    assert back.name == method and back.num_gaussians() == m.num_gaussians()
    for v in scene.test:
        a, b = m.render(v.camera), back.render(v.camera)
        assert float((a.rgb - b.rgb).abs().max()) <= 1e-6
        assert float((a.depth - b.depth).abs().max()) <= 1e-6
    if method != "3dgs":   # the learned α/β/γ themselves came back (not just their render)
        for name, value in m.parameter_values().items():
            assert torch.equal(value, back.parameter_values()[name]), name


@pytest.mark.parametrize("n", [0, 1])
@pytest.mark.parametrize("method", ["3dgs", "softmax_gs"])
def test_a_model_of_zero_or_one_gaussian_round_trips(scene, tmp_path, method, n):
    """A collapsed run exports (and reads back) what is left: none, or a single Gaussian."""
    m = create_method(method, scene, {"steps": 2, "densify": {"enabled": False}}, device="cpu")
    m.trainer.optimizer.keep(torch.arange(m.num_gaussians()) < n)
    m.train_step(0)
    s = read_ply(m.export_ply(tmp_path / "model.ply"))
    assert len(s) == n and s.mode == method and s.means.shape == (n, 3)
    back = GaussianSplatting.from_ply(scene, tmp_path / "model.ply", device="cpu")
    assert back.num_gaussians() == n
    v = scene.test[0]
    assert torch.equal(back.render(v.camera).rgb, m.render(v.camera).rgb)


def test_a_file_of_another_tool_with_normals_and_unknown_properties(scene, tmp_path):
    k = known_gaussians(scene, 50, 0)
    write_by_hand(tmp_path / "m.ply", **k, extras={"red": np.ones(50, np.float32)})
    s = read_ply(tmp_path / "m.ply")
    assert s.meta["ignored"] == "red" and s.meta["format"] == "binary_little_endian"
    # normals are optional: drop them
    v = plyfile.PlyData.read(str(tmp_path / "m.ply"))["vertex"]
    keep = [p.name for p in v.properties if p.name not in ("nx", "ny", "nz")]
    data = np.empty(len(v.data), dtype=[(q, "<f4") for q in keep])
    for q in keep:
        data[q] = v[q]
    plyfile.PlyData([plyfile.PlyElement.describe(data, "vertex")]).write(str(tmp_path / "nonormals.ply"))
    np.testing.assert_array_equal(read_ply(tmp_path / "nonormals.ply").means, k["means"])


@pytest.mark.parametrize("fmt", ["ascii", "binary_big_endian"])
def test_ascii_and_big_endian_files_read_as_the_little_endian_one(scene, tmp_path, fmt):
    k = known_gaussians(scene, 20, 1)
    write_by_hand(tmp_path / "le.ply", **k)
    write_by_hand(tmp_path / "other.ply", **k, fmt=fmt)
    a, b = read_ply(tmp_path / "le.ply"), read_ply(tmp_path / "other.ply")
    assert b.meta["format"] == fmt
    for name in ("means", "sh", "opacities", "scales", "quats"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


# ---- bad input ---------------------------------------------------------------------------------

def _good(scene, tmp_path, degree=1, n=10):
    k = known_gaussians(scene, n, degree)
    write_by_hand(tmp_path / "good.ply", **k)
    return tmp_path / "good.ply", k


def _rewrite(src, dst, rename=None, drop=(), values=None):
    v = plyfile.PlyData.read(str(src))["vertex"]
    names = [p.name for p in v.properties if p.name not in drop]
    data = np.empty(len(v.data), dtype=[((rename or {}).get(q, q), "<f4") for q in names])
    for q in names:
        data[(rename or {}).get(q, q)] = v[q]
    for q, val in (values or {}).items():
        data[q] = val
    plyfile.PlyData([plyfile.PlyElement.describe(data, "vertex")], byte_order="<").write(str(dst))
    return dst


def _error(path) -> str:
    with pytest.raises(PlyFormatError) as e:
        read_ply(path)
    msg = str(e.value)
    assert str(path) in msg and "expected" in msg
    return msg


def test_missing_and_misnamed_properties_are_named(scene, tmp_path):
    good, _ = _good(scene, tmp_path)
    msg = _error(_rewrite(good, tmp_path / "a.ply", drop=("rot_3",)))
    assert "missing properties ['rot_3']" in msg
    msg = _error(_rewrite(good, tmp_path / "b.ply", rename={"scale_0": "scale0"}))
    assert "['scale_0']" in msg
    msg = _error(_rewrite(good, tmp_path / "c.ply", rename={"f_rest_3": "f_rest_x"}))
    assert "misnamed property 'f_rest_x'" in msg
    msg = _error(_rewrite(good, tmp_path / "d.ply", drop=("f_rest_4",)))
    assert "not 0..7" in msg and "[4]" in msg


def test_an_f_rest_count_that_is_no_sh_degree(scene, tmp_path):
    good, _ = _good(scene, tmp_path)   # degree 1: 9 f_rest
    msg = _error(_rewrite(good, tmp_path / "a.ply", drop=("f_rest_8",)))
    assert "8 f_rest properties (no SH degree)" in msg and "0, 9, 24 or 45" in msg
    k = known_gaussians(scene, 5, 4)
    write_by_hand(tmp_path / "deg4.ply", **k)
    assert "degree 4, above the renderer's 3" in _error(tmp_path / "deg4.ply")


def test_non_finite_values_are_counted(scene, tmp_path):
    good, k = _good(scene, tmp_path)
    x = k["means"][:, 0].copy()
    x[[1, 3, 5]] = np.nan
    op = k["opacity_logit"].copy()
    op[2] = np.inf
    msg = _error(_rewrite(good, tmp_path / "a.ply", values={"x": x, "opacity": op}))
    assert "3 NaN and 1 inf value(s) in 2 properties" in msg and "x: 3 NaN" in msg


def test_empty_truncated_and_missing_files(scene, tmp_path):
    (tmp_path / "empty.ply").write_bytes(b"")
    assert "empty file" in _error(tmp_path / "empty.ply")
    good, _ = _good(scene, tmp_path, n=10)
    data = good.read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-50])
    msg = _error(tmp_path / "cut.ply")
    assert "truncated" in msg and "room for 9 vertices" in msg
    assert "declares 10 vertices × 104 bytes = 1040 bytes" in msg
    (tmp_path / "head.ply").write_bytes(data[:100])
    assert "not a readable PLY header" in _error(tmp_path / "head.ply")
    (tmp_path / "text.ply").write_bytes(b"hello\n")
    assert "expected 'ply'" in _error(tmp_path / "text.ply")
    assert "no such file" in _error(tmp_path / "nope.ply")


def test_half_a_softmax_pair_and_a_mode_comment_that_disagrees(scene, tmp_path):
    k = known_gaussians(scene, 5, 0)
    write_by_hand(tmp_path / "a.ply", **k, extras={"softmax_beta": np.zeros(5, np.float32)})
    assert "softmax_beta without its partner" in _error(tmp_path / "a.ply")
    s = read_ply(_good(scene, tmp_path)[0])
    s.meta["mode"] = "softmax_gs"
    write_ply(tmp_path / "b.ply", s)
    with pytest.raises(PlyFormatError, match="smgs mode softmax_gs' but the properties make a 3dgs model"):
        GaussianSplatting.from_ply(scene, tmp_path / "b.ply", device="cpu")


def test_a_failed_export_leaves_nothing_half_written(scene, tmp_path, monkeypatch):
    good, _ = _good(scene, tmp_path)
    s = read_ply(good)
    target = tmp_path / "out" / "model.ply"
    write_ply(target, s)
    before = target.read_bytes()

    def broken(self, stream):
        stream.write(b"ply\nformat binary_little_endian 1.0\n")
        raise OSError("disk full")

    monkeypatch.setattr(plyfile.PlyData, "write", broken)
    with pytest.raises(OSError, match="disk full"):
        write_ply(target, s)
    assert target.read_bytes() == before and os.listdir(target.parent) == ["model.ply"]
    monkeypatch.undo()
    s.means[0, 0] = np.nan
    with pytest.raises(PlyFormatError, match="1 NaN and 0 inf"):
        write_ply(tmp_path / "out" / "nan.ply", s)
    assert os.listdir(target.parent) == ["model.ply"]


# ---- every error names its file and what in it -------------------------------------------------

def test_a_finite_scale_whose_exp_overflows_names_the_file_and_property(scene, tmp_path):
    good, k = _good(scene, tmp_path)
    scales = k["log_scales"][:, 1].copy()
    scales[4] = 200.0                    # finite in the file, inf after exp: the renderer saw an unnamed inf
    msg = _error(_rewrite(good, tmp_path / "big.ply", values={"scale_1": scales}))
    assert "property scale_1 has 1 value(s) above 88.72" in msg and "vertex 4: scale_1 = 200" in msg
    with pytest.raises(PlyFormatError, match=r"big\.ply: property scale_1"):
        GaussianSplatting.from_ply(scene, tmp_path / "big.ply", device="cpu")


def test_an_ascii_header_claiming_10_12_vertices_is_refused_before_any_allocation(scene, tmp_path):
    good, k = _good(scene, tmp_path, n=3)
    write_by_hand(tmp_path / "a.ply", **k, fmt="ascii")
    data = (tmp_path / "a.ply").read_bytes().replace(b"element vertex 3\n", b"element vertex 1000000000000\n")
    (tmp_path / "huge.ply").write_bytes(data)
    msg = _error(tmp_path / "huge.ply")
    assert "declares 1000000000000 vertex rows" in msg and "as ASCII text" in msg


def test_random_bytes_named_ply_are_not_a_ply_file(tmp_path):
    junk = np.random.default_rng(0).bytes(4096)
    (tmp_path / "junk.ply").write_bytes(junk)
    assert "not a PLY file: it begins with" in _error(tmp_path / "junk.ply")
    (tmp_path / "junk2.ply").write_bytes(b"ply\n" + junk)   # the magic, then garbage: no codec traceback
    assert "not a readable PLY header" in _error(tmp_path / "junk2.ply")


@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_a_header_claiming_fewer_vertices_than_the_data_is_refused(scene, tmp_path, fmt):
    _, k = _good(scene, tmp_path, n=10)
    write_by_hand(tmp_path / "all.ply", **k, fmt=fmt)
    data = (tmp_path / "all.ply").read_bytes().replace(b"element vertex 10\n", b"element vertex 7\n")
    (tmp_path / "short.ply").write_bytes(data)
    msg = _error(tmp_path / "short.ply")
    assert ("declares 7 vertex rows" in msg and "room for 10" in msg) if fmt != "ascii" else \
        ("10 data rows, but the header declares 7 vertex rows" in msg)
