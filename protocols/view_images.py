"""Images a run leaves for the report's viewer (report.html), beside its ``renders/<view>.png``.

- ``renders/gt/<view>.png`` and ``renders/error/<view>.png`` for a few test views (evenly spaced
  over the name-sorted test set, so every method of a scene saves the same views): the 8-bit ground
  truth and the |render − ground truth| map on a fixed scale (``smgs.metrics.image.abs_error_map``),
  comparable between methods.
- ``consistency/strip.png`` + ``strip.json``: the frames i … i+step of the view-consistency video
  around its worst pair (highest flow-warped MSE), where popping shows.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from PIL import Image

from smgs.atomic import atomic_write_bytes, atomic_write_text
from smgs.metrics.image import ERROR_MAP_VMAX, abs_error_map, to_uint8

STRIP_TILE_WIDTH = 192


def viewer_indices(n: int, k: int) -> list[int]:
    """``k`` indices evenly spread over ``range(n)`` (first and last included when k >= 2)."""
    if n <= 0 or k <= 0:
        return []
    if k >= n:
        return list(range(n))
    if k == 1:
        return [0]
    return sorted({round(i * (n - 1) / (k - 1)) for i in range(k)})


def png_bytes(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


def save_view_images(renders_dir: Path, names: Sequence[str], renders: Sequence[torch.Tensor],
                     gts: Sequence[torch.Tensor], n_views: int) -> list[str]:
    """Ground truth and |error| map of ``n_views`` test views; returns the view stems saved."""
    order = sorted(range(len(names)), key=lambda i: str(names[i]))
    saved = []
    for k in viewer_indices(len(order), n_views):
        i = order[k]
        stem = Path(str(names[i])).stem
        gt = gts[i].detach().float().cpu().clamp(0, 1)
        pred = renders[i].detach().float().cpu().clamp(0, 1)
        atomic_write_bytes(renders_dir / "gt" / f"{stem}.png", png_bytes(to_uint8(gt).numpy()))
        atomic_write_bytes(renders_dir / "error" / f"{stem}.png", png_bytes(abs_error_map(pred, gt)))
        saved.append(stem)
    return saved


def save_popping_strip(out_dir: Path, render: Callable, cameras: Sequence, per_pair: Sequence[dict],
                       step: int) -> dict | None:
    """Render frames i … i+step around a flip, the pair whose popped pixels (leading splats swapped
    order) carry the most warped error, or where no pair has any, the pair with the highest MSE, and
    tile them into one PNG of tiles at most STRIP_TILE_WIDTH wide. ``per_pair``: the consistency
    scores' pairs (dicts with i, j, mse, pop). Returns what strip.json records, or None when no pair
    has a score."""
    scored = [p for p in per_pair if p.get("mse") is not None]
    if not scored:
        return None
    popped = [p for p in scored if (p.get("pop") or {}).get("popped")]
    if popped:
        worst = max(popped, key=lambda p: p["pop"]["popped_se"])
        why = f"the i → i+{step} pair whose popped pixels carry the most warped error"
    else:
        worst = max(scored, key=lambda p: p["mse"])
        why = f"the i → i+{step} pair with the highest warped MSE"
    i, j = int(worst["i"]), int(worst["j"])
    tiles = []
    with torch.no_grad():
        for k in range(i, j + 1):
            rgb = render(cameras[k])[0].detach().float().cpu().clamp(0, 1)
            img = Image.fromarray(to_uint8(rgb).numpy())
            if img.width > STRIP_TILE_WIDTH:
                img = img.resize((STRIP_TILE_WIDTH, max(1, round(img.height * STRIP_TILE_WIDTH / img.width))),
                                 Image.Resampling.BILINEAR)
            tiles.append(np.asarray(img))
    strip = np.concatenate(tiles, axis=1)
    info = {"frames": list(range(i, j + 1)), "pair": [i, j], "mse": float(worst["mse"]), "step": step,
            "tile_width": int(tiles[0].shape[1]), "why": why,
            "popped_pixels": int((worst.get("pop") or {}).get("popped", 0))}
    atomic_write_bytes(out_dir / "strip.png", png_bytes(strip))
    atomic_write_text(out_dir / "strip.json", json.dumps(info))
    return info


__all__ = ["ERROR_MAP_VMAX", "save_popping_strip", "save_view_images", "viewer_indices"]
