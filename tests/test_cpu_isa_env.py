"""``SMGS_CPU_ISA`` naming no SIMD path is refused as an unknown ``renderer.kernels`` is: by the
harness before any cell runs, and by the renderer itself, naming the variable and the values it
takes, never left to fall back to the PyTorch reference (a 16 s cell ran past 300 s at 4.2 GB)."""

from __future__ import annotations

import pytest
import torch

from smgs.raster import cpu, cpu_build


def test_a_bogus_path_stops_the_sweep_before_any_cell_runs_naming_the_variable(tmp_path, monkeypatch):
    from protocols.run import run_experiment

    monkeypatch.setenv(cpu_build.ISA_ENV, "bogus")
    with pytest.raises(SystemExit) as e:
        run_experiment(["grid.methods=[3dgs]", "report=false", "device=cpu", f"out_dir={tmp_path}/runs", "seeds=1",
                        "dataset.n_views=3", "dataset.width=16", "dataset.height=16", "protocol.steps=1",
                        "protocol.schedule_steps=null", "eval.fps_repeats=1", "eval.flip=false",
                        "eval.consistency=false", "eval.fractions=[1.0]"])
    msg = str(e.value)
    assert msg.startswith("invalid config, nothing was run:")
    assert ("SMGS_CPU_ISA='bogus' (an environment variable) is not a CPU SIMD path; it takes one of avx512, avx2, "
            f"neon, scalar (this host runs {', '.join(cpu_build.host_isas())}), or unset it to take the best") in msg
    assert not (tmp_path / "runs").exists()


def test_a_path_this_cpu_cannot_run_stops_a_local_sweep(tmp_path, monkeypatch):
    from protocols.validate import cpu_isa_problems

    foreign = next((i for i in cpu_build.ISAS if i not in cpu_build.host_isas()), None)
    if foreign is None:
        pytest.skip("this host runs every path")
    monkeypatch.setenv(cpu_build.ISA_ENV, foreign)
    assert f"cannot run the {foreign} path" in cpu_isa_problems({"executor": {"kind": "local"}})[0]
    assert cpu_isa_problems({"executor": {"kind": "slurm"}}) == []   # the cluster's nodes decide


def test_the_renderer_refuses_a_bogus_path_instead_of_the_reference(monkeypatch):
    from smgs.camera import Camera
    from smgs.raster import rasterize

    monkeypatch.setenv(cpu_build.ISA_ENV, "bogus")
    with pytest.raises(ValueError, match=r"SMGS_CPU_ISA='bogus' \(an environment variable\) is not a CPU SIMD path"):
        cpu.is_available()
    cam = Camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0], 30.0, 30.0, 24, 18)
    n = 4
    with pytest.raises(ValueError, match="SMGS_CPU_ISA='bogus'"):   # "auto" on a CPU tensor: not the reference
        rasterize(torch.zeros(n, 3), torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 3), 0.2),
                  torch.full((n,), 0.5), torch.rand(n, 1, 3), cam, mode="3dgs", sh_degree=0, backend="auto")
