"""Render a small synthetic scene with the four methods and save PNGs (no download needed).

python -m smgs.demo --out demo_out
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from smgs.camera import Camera
from smgs.raster import MODES, rasterize


def synthetic_gaussians(n: int = 400, seed: int = 0) -> dict[str, torch.Tensor]:
    """Flat-coloured blobs on three overlapping discs at different depths."""
    g = torch.Generator().manual_seed(seed)
    centres = torch.tensor([[-0.4, -0.2, 3.0], [0.3, 0.1, 3.4], [0.0, 0.35, 2.6]])
    palette = torch.tensor([[0.9, 0.2, 0.2], [0.2, 0.7, 0.3], [0.2, 0.3, 0.9]])
    k = torch.randint(0, 3, (n,), generator=g)
    r = 0.45 * torch.rand(n, generator=g).sqrt()
    th = 2 * math.pi * torch.rand(n, generator=g)
    means = centres[k] + torch.stack([r * th.cos(), r * th.sin(), 0.02 * torch.randn(n, generator=g)], 1)
    return dict(means=means, quats=torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=1),
                scales=0.05 * torch.exp(0.3 * torch.randn(n, 3, generator=g)),
                opacities=0.4 + 0.5 * torch.rand(n, generator=g), colors=palette[k],
                alpha=torch.full((n,), 3.0), beta=torch.full((n,), 20.0), gamma=torch.full((n,), 5.0))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="demo_out")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--backend", default="auto")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    s = synthetic_gaussians()
    cam = Camera.look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], fx=args.size, fy=args.size,
                         width=args.size, height=args.size)
    for mode in MODES:
        t0 = time.perf_counter()
        r = rasterize(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], cam,
                      s["alpha"], s["beta"], s["gamma"], mode=mode, backend=args.backend)
        ms = 1e3 * (time.perf_counter() - t0)
        img = (r.rgb.clamp(0, 1).detach().numpy() * 255 + 0.5).astype(np.uint8)
        Image.fromarray(img).save(out / f"{mode}.png")
        print(f"{mode:13s} {ms:8.1f} ms  splats/pixel {r.stats.splats_per_pixel:5.2f}  -> {out / (mode + '.png')}")


if __name__ == "__main__":
    main()
