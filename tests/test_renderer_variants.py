"""The renderer's backends and variants in one registry (``smgs.raster.backends``), set from a run's
config (``backend``, ``renderer.kernels``, ``renderer.glue``) and recorded in every results.json and
in the report's environment table: a protocol cell trained with each CUDA variant on the stand-in
device (tests/device_mix.py; the bindings are tests/cuda_standin.py's and tests/cuda_v2_standin.py's)
and one on the CPU each say which rendered them."""

from __future__ import annotations

import json
import re

import pytest
import torch
from cuda_v2_standin import OnHost, StandInCompositing, StandInProjection
from device_mix import OTHER, simulated_gpu

from smgs.raster import Renderer, backends, cuda_v2, projection_cuda, render_variant

# (the renderer section, what rendered) per CUDA variant
VARIANTS = [({}, "cuda (kernels default, glue verified)"),
            ({"glue": "lean"}, "cuda (kernels default, glue lean)"),
            ({"kernels": "v2"}, "cuda (kernels v2, glue verified)"),
            ({"kernels": "v2", "glue": "lean"}, "cuda (kernels v2, glue lean)")]


def test_the_registry_resolves_each_backend_and_variant():
    assert backends.BACKEND_NAMES == ("reference", "cpu", "cuda")
    assert backends.BACKENDS["cuda"].axes() == {"kernels": ("default", "v2"), "glue": ("verified", "lean")}
    assert render_variant("auto", "cpu").describe() == "cpu"
    assert render_variant(Renderer("reference", kernels="v2", glue="lean"), "cpu").describe() == "reference"
    v = backends.variant(Renderer(kernels="v2", glue="lean"), "cuda")
    assert v.describe() == "cuda (kernels v2, glue lean)" and v.lean(OTHER) and not v.lean(torch.device("cpu"))
    assert backends.variant(Renderer(), "cuda").describe("per_pixel") == \
        "cuda (kernels default, glue verified, per-pixel order on host copies (cpu, else reference))"
    with pytest.raises(ValueError, match=r"glue='quick' names no glue variant of any renderer backend; choose one "
                                         r"of lean, verified"):
        Renderer(glue="quick")


def test_an_unknown_variant_in_a_config_is_refused_naming_it():
    from protocols.validate import renderer_problems

    assert renderer_problems({"backend": "auto", "renderer": {"kernels": "v2", "glue": "lean"}}) == []
    assert renderer_problems({"renderer": {"kernels": "v3"}}) == [
        "renderer.kernels='v3' names no kernels variant of any renderer backend; choose one of default, v2 "
        "(docs/renderer.md#backends-and-variants)"]
    assert renderer_problems({"renderer": {"colour": "x"}}) == ["renderer.colour: not a renderer setting; known: "
                                                               "kernels, glue"]


def _payload(tmp_path, seed: int, device: str, section: dict) -> dict:
    from hydra import compose, initialize_config_dir

    from protocols.run import CONFIG_DIR, plan

    ov = ["+experiment=smoke", "grid.methods=[softmax_gs]", "grid.seeds_of={}", f"seed={seed}", "protocol.steps=3",
          "report=false", "eval.fps_repeats=1", "eval.fractions=[1.0]", "eval.flip=false", "device=cpu",
          f"out_dir={tmp_path}", *(f"renderer.{k}={v}" for k, v in section.items())]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        (payload,) = plan(compose(config_name="config", overrides=ov), ov)[1]
    payload["config"]["device"] = device
    return payload


def _run(payload, monkeypatch, on_other: bool) -> tuple[dict, dict]:
    """The cell's summary, and what its renders called on the stand-in device: the default and the v2
    bindings' forwards, and the host waits (the lean glue waits less)."""
    from protocols.cell import run_cell

    if not on_other:
        return run_cell(payload), {}
    with simulated_gpu(monkeypatch) as m:   # the v2 bindings' stand-ins too, computing on the host
        proj = OnHost(StandInProjection(), m)
        comp = OnHost(StandInCompositing(), m, "binding forward: the pair count",
                      "binding backward: the most crowded pixel's count")
        monkeypatch.setattr(projection_cuda, "extension", lambda: proj)
        monkeypatch.setattr(cuda_v2, "extension", lambda t_min=None: comp)
        summary = run_cell(payload)
        return summary, {"default": m.bindings["forward"], "v2": comp.base.calls.count("forward_v2"),
                         "waits": sum(v for k, v in m.counts.items() if "non_blocking" not in k)}


def test_a_result_of_each_cuda_variant_and_of_the_cpu_records_which_in_results_json_and_report_md(
        tmp_path, monkeypatch):
    """Each cell trains and is scored on its renderer: the four CUDA variants on the stand-in device,
    one run on the CPU. results.json's versions name the backend and its variants (and the CPU's
    SIMD path), and report.md's environment table lists every one of them."""
    import protocols.train_loop as tl
    from protocols.results import read_result
    from reports.build import build_report
    from smgs.data.procedural import make_procedural_scene

    for k in (backends.KERNELS_ENV, backends.GLUE_ENV):
        monkeypatch.delenv(k, raising=False)
    scene = make_procedural_scene(n_views=4, size=(24, 16), n_points=150, n_trajectory=4, supersample=1)
    monkeypatch.setattr(tl, "load_scene_for", lambda cfg: scene)
    cells = [(section, str(OTHER), want) for section, want in VARIANTS] + [({}, "cpu", "cpu")]
    recorded, calls = [], []
    for seed, (section, device, want) in enumerate(cells):
        payload = _payload(tmp_path, seed, device, section)
        with monkeypatch.context() as mp:
            summary, called = _run(payload, mp, on_other=device != "cpu")
        calls.append(called)
        run_dir = tmp_path / payload["key"]
        assert summary["status"] == "ok", (run_dir / "log.txt").read_text()[-3000:]
        res = read_result(run_dir / "results.json")
        assert res.versions["renderer"] == want and res.versions["backend"] == want.split()[0]
        assert json.loads((run_dir / "results.json").read_text())["config"]["renderer"] == \
            {"kernels": "default", "glue": "verified", **section}
        recorded.append(res)
    assert recorded[-1].versions["cpu_isa"] in ("avx512", "avx2", "neon", "scalar")
    # what the record says is what rendered: the default bindings or the v2 ones, fewer waits when lean
    (default, lean, v2, v2_lean) = calls[:4]
    assert default["default"] and lean["default"] and not default["v2"] and not lean["v2"]
    assert v2["v2"] and v2_lean["v2"] and not v2["default"] and not v2_lean["default"]
    assert lean["waits"] < default["waits"] and v2_lean["waits"] < v2["waits"], calls
    md = build_report(tmp_path, stability="not wanted here").read_text()
    env = md.split("## Environment", 1)[1]
    line = re.search(r"^\| renderer \(backend, variants\) \| ([^|]*) \|", env, re.M)[1]
    assert line.startswith("mixed: ") and all(f"{want} (1 runs)" in line for _, _, want in cells), line
    assert re.search(r"^\| CPU SIMD path \| (avx512|avx2|neon|scalar) \|", env, re.M)
    assert "mixes renderer backends or variants (cpu; cuda (kernels default, glue lean);" in md


def test_a_non_default_variant_is_part_of_a_cuda_cells_identity_and_the_defaults_hash_as_before(tmp_path, monkeypatch):
    """The default variants hash as a config without the ``renderer`` section (results computed before
    it existed stay valid); on a CUDA device another kernel set or glue is another result (on the CPU
    they render nothing differently: tests/test_identity.py)."""
    from protocols.cell import result_hash

    for k in (backends.KERNELS_ENV, backends.GLUE_ENV):
        monkeypatch.delenv(k, raising=False)
    cfg = _payload(tmp_path, 0, "cuda:0", {})["config"]
    before = {k: v for k, v in cfg.items() if k != "renderer"}
    assert cfg["renderer"] == {"kernels": "default", "glue": "verified"} and result_hash(cfg) == result_hash(before)
    hashes = {result_hash(_payload(tmp_path, 0, "cuda:0", s)["config"]) for s, _ in VARIANTS}
    assert len(hashes) == 4 and result_hash(cfg) in hashes
    monkeypatch.setenv(backends.KERNELS_ENV, "v2")   # the environment's value is the config's, hashed as such
    assert result_hash(_payload(tmp_path, 0, "cuda:0", {})["config"]) == \
        result_hash(_payload(tmp_path, 0, "cuda:0", {"kernels": "v2"})["config"]) != result_hash(cfg)
