"""A cell's identity, defined once: what skips a finished cell, what a checkpoint must match to be
resumed, and what the seeds of one report row must share to be pooled. Plain data in and out (a
cell's resolved config as a dict, the method's resolved settings, the inputs' fingerprint,
``smgs.data.fingerprint``): no Hydra, no harness; the runner (``protocols.cell``), the reports
(``reports.runs``) and ``smgs.results`` read it from here.

A cell is its resolved config that changes numbers, plus the fingerprint of the inputs it read.
What changes no number is named here, once:

- ``VOLATILE``: top-level keys about where and how a sweep runs; never part of a cell.
- ``NO_NUMBER``: keys that change no number (which files a run writes beside its numbers). A cell is
  hashed with them at their defaults, so results hashed before they were named here keep their
  hash; they are not in the pooling key.
- the renderer's variants (``renderer.kernels``, ``renderer.glue``, also as the environment's
  ``SMGS_CUDA_KERNELS`` / ``SMGS_CUDA_GLUE``) where the cell's renderer has no such axis: a CUDA
  kernel set asked for a CPU run renders nothing differently (``smgs.raster.backends``).
- ``LOCATIONS``: where the inputs lie. Hashed (a scene moved elsewhere is rerun), not pooled on:
  the inputs' fingerprint says whether two copies of a scene hold the same.

The hash of a cell (``cell_key``) is the one recorded with its result and checkpoint; a result or
checkpoint recorded under the hash an earlier smgs gave the same computation (``CellKey.earlier``)
is this cell's too, so an upgrade retrains nothing whose numbers it does not change.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from typing import Any, Iterable

VOLATILE: tuple[str, ...] = ("force", "executor", "report", "report_builder", "out_dir", "data_root", "on_missing",
                             "grid", "seeds", "experiment_name", "checkpoint_every", "export_ply", "on_busy")
"""Top-level keys of a cell's config that say where and how it runs, not what it computes."""

NO_NUMBER: dict[str, Any] = {
    "eval.viewer_views": 3,      # how many test views' ground truth and error maps are saved (report.html)
    "eval.save_renders": True,   # whether the test renders and the popping strip are saved as PNGs
}
"""Dotted keys that change no number, each with its default (configs/config.yaml)."""

LOCATIONS: tuple[str, ...] = ("dataset.path", "ply.path")
"""Dotted keys that say where a cell read its inputs, not what they hold."""

NOT_SET = "<not set>"


def config_hash(config: dict) -> str:
    """Stable hash of a plain dict (key order does not matter)."""
    blob = json.dumps(config, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]


# ---- the config that changes numbers -----------------------------------------------------------

def unused_variants(cfg: dict) -> set[str]:
    """The renderer's variant axes (``kernels``, ``glue``) that the cell's renderer does not have: all
    of them on a CPU run (the CPU and reference backends have none). A device or backend still
    ``auto`` may be CUDA: its variants count."""
    from smgs.raster.backends import AXES, BACKENDS

    device, backend = str(cfg.get("device") or "auto"), str(cfg.get("backend") or "auto")
    if backend == "auto":
        backend = "cpu" if device.split(":")[0] == "cpu" else "cuda"
    spec = BACKENDS.get(backend)
    return set() if spec is None else set(AXES) - set(spec.axes())


def _renderer_section(cfg: dict, earlier: bool) -> dict | None:
    """The ``renderer`` section as identified: None where every variant asks for the default (as
    results were hashed before variants were settings) or, unless ``earlier``, is unused."""
    from smgs.raster.backends import is_default

    section = cfg.get("renderer")
    if not section or not isinstance(section, dict):
        return section or None
    unused = set() if earlier else unused_variants(cfg)
    if all(k in unused or is_default(k, v) for k, v in section.items()):
        return None
    return {k: v for k, v in section.items() if k not in unused}


def _with_dotted(cfg: dict, values: dict[str, Any]) -> dict:
    """``cfg`` with each dotted key that it has set to ``values``' value."""
    out = dict(cfg)
    for key, value in values.items():
        head, _, rest = key.partition(".")
        if head in out and rest and isinstance(out[head], dict):
            out[head] = _with_dotted(out[head], {rest: value})
        elif head in out and not rest:
            out[head] = value
    return out


def canonical_config(cfg: dict, earlier: bool = False) -> dict:
    """A cell's config as it identifies the cell: without ``VOLATILE``, the ``NO_NUMBER`` keys at their
    defaults, the renderer's unused or default variants left out. ``earlier``: as smgs hashed cells
    before ``NO_NUMBER`` and the unused variants were named (``CellKey.earlier``)."""
    out = {k: v for k, v in cfg.items() if k not in VOLATILE}
    if not earlier:
        out = _with_dotted(out, NO_NUMBER)
    renderer = _renderer_section(cfg, earlier)
    if renderer is None:
        out.pop("renderer", None)
    else:
        out["renderer"] = renderer
    return out


def _settings_form(resolved: dict, cfg: dict, earlier: bool) -> dict:
    """The method's resolved settings as hashed: the form finished results were hashed with
    (``smgs.train.config.earlier_train_keys``), unused renderer variants unset."""
    from smgs.train.config import earlier_train_keys

    if not earlier:
        resolved = {**resolved, **{axis: None for axis in unused_variants(cfg) if axis in resolved}}
    return earlier_train_keys(resolved)


def cell_identity(cfg: dict, budget: dict | None = None, resolved: dict | None = None,
                  earlier: bool = False) -> dict:
    """What a cell's hash is made of: its ``canonical_config``, its budget as identified
    (``protocols.sections.BudgetConfig.identity``: what the budget sets, not its file) and the
    method's complete resolved settings (defaults included, so that a changed default retrains)."""
    ident = canonical_config(cfg, earlier)
    if budget is not None:
        ident["budget"] = budget
    if resolved is not None:
        ident["resolved_settings"] = _settings_form(resolved, cfg, earlier)
    return ident


# ---- what a finished result or checkpoint must match ---------------------------------------------

@dataclass(frozen=True)
class CellKey:
    """What a finished result or a checkpoint must have been made under to be this cell's: its hash
    (or a hash an earlier smgs gave the same computation) and the fingerprint of its inputs."""

    hash: str
    earlier: tuple[str, ...] = ()
    inputs: dict | None = None

    def mismatch(self, config_hash: str | None, inputs: dict | None) -> str | None:
        """Why a result or checkpoint recorded with ``config_hash`` and ``inputs`` is not this cell's
        (None when it is). A record without a fingerprint (written before inputs were recorded) is
        not compared on its inputs."""
        if config_hash != self.hash and config_hash not in self.earlier:
            return f"its config {config_hash or '<unrecorded>'} is not this cell's {self.hash}"
        changed = inputs_changed(inputs, self.inputs)
        return f"the inputs changed since it was computed: {changed}" if changed else None

    def checkpoint_fields(self) -> dict[str, Any]:
        """What a checkpoint records of the cell it belongs to."""
        return {"config_hash": self.hash, "inputs": {"digest": (self.inputs or {}).get("digest")}}


def cell_key(cfg: dict, budget: dict | None = None, resolved: dict | None = None,
             inputs: dict | None = None) -> CellKey:
    """A cell's ``CellKey`` from its resolved config, budget identity, the method's resolved settings
    and its inputs' fingerprint."""
    now = config_hash(cell_identity(cfg, budget, resolved))
    before = config_hash(cell_identity(cfg, budget, resolved, earlier=True))
    return CellKey(now, () if before == now else (before,), inputs)


SHOWN_FILES = 3


def inputs_changed(old: dict | None, new: dict | None) -> str | None:
    """The files that differ between two fingerprints, named (None when they agree, or one of them
    lists no files and records no digest to compare)."""
    if not old or not new:
        return None
    a, b = old.get("files"), new.get("files")
    if not isinstance(a, dict) or not isinstance(b, dict):
        da, db = old.get("digest"), new.get("digest")
        return None if da is None or db is None or da == db else f"their digest {da} is now {db}"
    if a == b:
        return None
    parts = [f"{n} (changed)" for n in a if n in b and a[n] != b[n]] + [f"{n} (gone)" for n in a if n not in b] \
        + [f"{n} (new)" for n in b if n not in a]
    more = f" and {len(parts) - SHOWN_FILES} more" if len(parts) > SHOWN_FILES else ""
    return ", ".join(parts[:SHOWN_FILES]) + more


# ---- pooling seeds -----------------------------------------------------------------------------

def pooling_key(cfg: dict, hparams: str = "") -> dict[str, str]:
    """What the seeds of one report row must share, as dotted keys: the ``canonical_config`` without
    the seed, the ``NO_NUMBER`` keys and the ``LOCATIONS``, the device by its kind (``cuda:1`` is
    ``cuda``), and the method's hyperparameter set."""
    cfg = {k: v for k, v in canonical_config(cfg).items() if k != "seed"}
    if isinstance(cfg.get("device"), str):
        cfg["device"] = cfg["device"].split(":")[0]
    flat = flatten(cfg)
    for key in (*NO_NUMBER, *LOCATIONS):
        flat.pop(key, None)
    if hparams:
        flat["hparams"] = repr(hparams)
    return flat


def flatten(cfg: dict) -> dict[str, str]:
    """A nested dict as dotted keys, each value by its repr."""
    flat: dict[str, str] = {}

    def walk(prefix: str, x: Any) -> None:
        if isinstance(x, dict) and x:
            for k, v in x.items():
                walk(f"{prefix}.{k}" if prefix else str(k), v)
        else:
            flat[prefix] = repr(x)

    walk("", cfg)
    return flat


@dataclass(frozen=True)
class SeedRecord:
    """One seed of a row as its result records it: the seed, its config, its hyperparameter set and
    its inputs' fingerprint (empty where not recorded)."""

    seed: int
    config: dict
    hparams: str = ""
    inputs: dict | None = None


def seeds_difference(seeds: Iterable[SeedRecord], shown: int = 3, width: int = 60) -> str | None:
    """Why these seeds of one row must not be pooled: the keys of ``pooling_key`` in which they
    differ, each seed's value named, else the input files whose content differs (None when they
    agree; seeds that record no config, or no fingerprint, are not compared on it)."""
    seeds = sorted(seeds, key=lambda s: s.seed)
    configs = [(s.seed, pooling_key(s.config, s.hparams)) for s in seeds if s.config]
    if len(configs) >= 2:
        keys = sorted({k for _, c in configs for k in c})
        differ = [k for k in keys if len({c.get(k, NOT_SET) for _, c in configs}) > 1]
        if differ:
            parts = [f"{k} ({_by_value([(seed, c.get(k, NOT_SET)) for seed, c in configs], width)})"
                     for k in differ[:shown]]
            more = f"; and {len(differ) - shown} more key(s)" if len(differ) > shown else ""
            return ("seeds trained under different configs, not pooled: " + "; ".join(parts) + more
                    + " (rerun them under one config)")
    return _inputs_difference([s for s in seeds if s.inputs and isinstance(s.inputs.get("files"), dict)], shown)


def _inputs_difference(seeds: list[SeedRecord], shown: int) -> str | None:
    if len(seeds) < 2:
        return None
    names = sorted({n for s in seeds for n in s.inputs["files"]})

    def content(s: SeedRecord, n: str) -> str:
        f = s.inputs["files"].get(n)
        return "absent" if f is None else f"sha256 {str(f.get('sha256'))[:12]}, {f.get('size')} bytes"

    differ = [n for n in names if len({content(s, n) for s in seeds}) > 1]
    if not differ:
        return None
    parts = [f"{n} ({_by_value([(s.seed, content(s, n)) for s in seeds], 60)})" for n in differ[:shown]]
    more = f"; and {len(differ) - shown} more file(s)" if len(differ) > shown else ""
    return ("seeds trained on different inputs, not pooled: " + "; ".join(parts) + more
            + " (rerun them on one copy of the scene)")


def _by_value(values: list[tuple[int, str]], width: int) -> str:
    by_value: dict[str, list[int]] = {}
    for seed, v in values:
        by_value.setdefault(v, []).append(seed)
    return "; ".join(f"seed{'s' if len(ss) > 1 else ''} {', '.join(map(str, ss))}: {_one_line(v, width)}"
                     for v, ss in by_value.items())


def _one_line(text: str, limit: int) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 1] + "…"
