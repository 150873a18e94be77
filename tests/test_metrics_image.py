"""8-bit quantisation, PSNR, SSIM (cross-checked against scikit-image and kornia), FLIP guards."""

from __future__ import annotations

import math

import kornia
import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from smgs.metrics import flip as flip_mod
from smgs.metrics.flip import flip_error_map, flip_mean
from smgs.metrics.image import evaluate_images, png_roundtrip, psnr, quantize_8bit, to_uint8
from smgs.metrics.result import Missing
from smgs.metrics.ssim import ssim_map


def _photo_pair(dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    from skimage import data

    a = data.astronaut()[100:196, 200:328].astype(np.float64) / 255.0
    yy, xx = np.mgrid[: a.shape[0], : a.shape[1]]
    b = np.clip(a + 0.08 * np.sin(xx * 0.7 + yy * 1.3)[..., None], 0, 1)
    return torch.from_numpy(a).to(dtype), torch.from_numpy(b).to(dtype)


def test_quantize_equals_png_roundtrip():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(17, 23, 3, generator=g) * 1.2 - 0.1  # includes out-of-range values
    img[0, 0] = torch.tensor([0.5 / 255, 1.5 / 255, 254.5 / 255])  # rounding boundaries
    assert torch.equal(quantize_8bit(img), png_roundtrip(img))
    assert to_uint8(img)[0, 0].tolist() == [1, 2, 255]  # ×255 + 0.5, truncated (save_image)
    q = quantize_8bit(img)
    assert torch.equal(quantize_8bit(q), q)  # idempotent on 8-bit images


def test_psnr_per_image_then_mean():
    gt = torch.full((8, 8, 3), 100 / 255)
    preds = [gt + 10 / 255, gt + 1 / 255]
    res = evaluate_images(preds, [gt, gt], lpips=Missing("not under test"), flip=False)
    expected = [20 * math.log10(255 / 10), 20 * math.log10(255 / 1)]
    assert res.psnr == [pytest.approx(e, abs=1e-4) for e in expected]
    # the mean of per-image PSNRs, not the PSNR of the mean MSE
    assert res.means()["psnr"] == pytest.approx(sum(expected) / 2, abs=1e-4)
    assert psnr(gt, gt) == math.inf
    assert res.to_json()["mean"]["lpips_vgg_v0.1"] == {"missing": "not under test"}


def test_ssim_agrees_with_scikit_image_and_kornia_on_the_interior():
    """Why the means differ: all three use the same 11×11 Gaussian window (σ 1.5), C1 = 0.01²,
    C2 = 0.03² and population (not sample) covariances, so the SSIM *maps* agree wherever the
    window lies inside the image. They differ at the border: 3DGS (and smgs) zero-pads and averages
    the full map; scikit-image reflects and then crops (win-1)/2 = 5 px before averaging; kornia
    reflects and keeps the full map ('same') or crops 5 px ('valid'). Zero padding darkens the
    local means near the edge, so the 3DGS mean is not equal to either library's on any image
    whose border is not constant. scikit-image's *defaults* differ further (7×7 uniform window,
    sample covariance) and must not be used for comparison with 3DGS numbers."""
    a, b = _photo_pair()
    ours = ssim_map(a, b)  # float64
    inner = ours[5:-5, 5:-5]
    sk = structural_similarity(a.numpy(), b.numpy(), channel_axis=2, data_range=1.0,
                               gaussian_weights=True, sigma=1.5, use_sample_covariance=False)
    assert float(inner.mean()) == pytest.approx(sk, abs=1e-10)
    A, B = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
    k_valid = kornia.metrics.ssim(A, B, 11, padding="valid")[0].permute(1, 2, 0)
    k_same = kornia.metrics.ssim(A, B, 11, padding="same")[0].permute(1, 2, 0)
    # kornia 0.9 takes a separate CPU code path whose rounding differs by ~2e-7 even in float64
    # (its Gaussian window equals ours exactly); the formula is the same.
    torch.testing.assert_close(k_valid, inner, atol=1e-6, rtol=0)
    torch.testing.assert_close(k_same[5:-5, 5:-5], inner, atol=1e-6, rtol=0)
    assert not torch.allclose(k_same[:5], ours[:5], atol=1e-3)  # the border is where they differ
    assert abs(float(ours.mean()) - sk) > 1e-3
    # float32 (what the metric runs in) stays close to float64: E[x²] - μ² cancels a little
    a32, b32 = a.float(), b.float()
    assert float(ssim_map(a32, b32).mean()) == pytest.approx(float(ours.mean()), abs=1e-4)
    assert float(ssim_map(a32, a32).mean()) == pytest.approx(1.0, abs=1e-6)


def test_evaluate_images_quantises_and_keeps_per_view_values():
    a, b = (x.float() for x in _photo_pair())
    res = evaluate_images([b, a], [a, a], names=["x", "y"], lpips=Missing("skip"))
    qa, qb = quantize_8bit(a), quantize_8bit(b)
    assert res.names == ["x", "y"] and res.quantized
    assert res.psnr[0] == pytest.approx(psnr(qb, qa)) and res.psnr[1] == math.inf
    assert res.ssim[1] == pytest.approx(1.0, abs=1e-6)
    assert res.flip[1] == 0.0 and 0.0 < res.flip[0] < 1.0
    assert res.flip_name == "flip_ldr_ppd67"
    with pytest.raises(ValueError, match="shape"):
        evaluate_images([a], [a[:-1]], lpips=Missing("skip"))


def test_flip_raw_map_mask_and_package_mean():
    import flip_evaluator

    a, b = (x.float().numpy() for x in _photo_pair())
    err = flip_error_map(a, b)
    assert err.shape == a.shape[:2] and err.dtype == np.float32
    _, pkg_mean, _ = flip_evaluator.evaluate(np.ascontiguousarray(a, np.float32),
                                             np.ascontiguousarray(b, np.float32), "LDR",
                                             applyMagma=False, parameters={"ppd": 67.0})
    assert float(err.mean()) == pytest.approx(pkg_mean, rel=1e-5)
    mask = np.zeros(a.shape[:2], bool)
    mask[10:30, 20:60] = True
    assert flip_mean(a, b, mask) == pytest.approx(float(err[mask].mean()))
    assert np.all(flip_error_map(a, a) == 0)


def test_flip_rejects_bad_input_instead_of_exiting(monkeypatch):
    a = np.random.default_rng(0).random((8, 9, 3), dtype=np.float32)
    for bad, match in [(a * 2, r"\[0, 1\]"), (a[..., :2], r"\[H, W, 3\]"), (a[:4], "shape")]:
        with pytest.raises(ValueError, match=match):
            flip_error_map(a, bad)
    nan = a.copy()
    nan[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        flip_error_map(a, nan)
    with pytest.raises(ValueError, match="ppd"):
        flip_error_map(a, a, ppd=0.0)
    with pytest.raises(ValueError, match="selects no pixel"):
        flip_mean(a, a, np.zeros((8, 9), bool))

    def exits(*args, **kwargs):
        raise SystemExit(1)

    import flip_evaluator

    monkeypatch.setattr(flip_evaluator, "evaluate", exits)
    with pytest.raises(ValueError, match="rejected"):
        flip_error_map(a, a)
    assert flip_mod.flip_available() is True
