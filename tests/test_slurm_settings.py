"""What a cell's SLURM job asks for (protocols.slurm_settings), what the cell's threads follow
(protocols.job_cpus), and how sbatch's refusals are worded: no SLURM needed (tests/test_slurm_executor.py
runs the same against a real one)."""

import pytest

from protocols.job_cpus import job_cpus, slurm_job, train_conditions
from protocols.slurm_settings import SlurmSettings, refusal

CONFIG = {"partition": "debug", "timeout_min": 240, "max_requeues": 3, "signal_lead_s": 90, "gpus_per_node": "auto",
          "cpus_per_task": 2, "mem_gb": 8, "sbatch": {}, "folder": "runs/x/_submitit"}


def test_gpus_follow_the_cells_device():
    s = SlurmSettings.of(CONFIG)
    assert [s.gpus_for(d, False) for d in ("cpu", "cuda", "cuda:0", "cuda:2", "auto", None)] == [0, 1, 1, 3, 0, 0]
    assert s.gpus_for("auto", True) == 1 and s.gpus_for("auto", None) == 0
    assert SlurmSettings.of({**CONFIG, "gpus_per_node": 2}).gpus_for("cpu", False) == 2
    assert SlurmSettings.of({**CONFIG, "gpus_per_node": None}).gpus_for("cuda", True) == 0
    params = s.parameters(0, "smgs-x")
    assert "gpus_per_node" not in params and params["cpus_per_task"] == 2 and params["mem"] == "8192M"
    assert params["additional_parameters"] == {"requeue": True} and params["partition"] == "debug"
    with_gpu = SlurmSettings.of({**CONFIG, "sbatch": {"account": "lab"}}).parameters(1, "smgs-x")
    assert with_gpu["gpus_per_node"] == 1 and with_gpu["additional_parameters"] == {"requeue": True, "account": "lab"}


@pytest.mark.parametrize("minutes, lead, fits", [(240, 90, 90), (1, 90, 15), (2, 90, 30), (5, 90, 75), (6, 90, 90),
                                                 (30, 1200, 450), (60, 1200, 600), (240, 7000, 2760)])
def test_the_warning_fits_the_limit(minutes, lead, fits):
    s = SlurmSettings.of({**CONFIG, "timeout_min": minutes, "signal_lead_s": lead})
    assert s.lead_s() == fits
    # submitit takes a warning for the time limit from 80 % of the limit or its last 10 minutes on;
    # SLURM may send it up to a minute early
    assert 60 * minutes - fits - 60 >= min(0.8 * 60 * minutes, 60 * minutes - 600)


@pytest.mark.parametrize("key, value, words", [
    ("timeout_min", 0, "executor.slurm.timeout_min=0: give a whole number >= 1"),
    ("max_requeues", -1, "executor.slurm.max_requeues=-1: give a whole number >= 0"),
    ("cpus_per_task", "four", "executor.slurm.cpus_per_task='four'"),
    ("gpus_per_node", "some", "executor.slurm.gpus_per_node='some': give a whole number >= 0 or auto"),
    ("mem_gb", 0, "executor.slurm.mem_gb=0: give each job's memory in GB"),
    ("sbatch", "account=x", "give further sbatch options as a mapping"),
    ("acount", "lab", "executor.slurm.acount is no setting of the SLURM executor"),
])
def test_impossible_settings_name_the_key(key, value, words):
    with pytest.raises(ValueError, match=words.replace("(", r"\(").replace("[", r"\[")):
        SlurmSettings.of({**CONFIG, key: value})


@pytest.mark.parametrize("said, words", [
    ("sbatch: error: Batch job submission failed: Invalid generic resource (gres) specification",
     "executor.slurm.gpus_per_node=auto with device=cuda. On CPU nodes run the cells on the CPU (device=cpu"),
    ("sbatch: error: invalid partition specified: gpux\nsbatch: error: Batch job submission failed: Invalid "
     "partition name specified", "sbatch refused executor.slurm.partition=debug (invalid partition specified: gpux;"),
    ("sbatch: error: Batch job submission failed: Requested time limit is invalid (missing or exceeds some limit)",
     "sbatch refused executor.slurm.timeout_min=240 on partition debug"),
    ("sbatch: error: Batch job submission failed: Requested node configuration is not available",
     "lower executor.slurm.cpus_per_task or executor.slurm.mem_gb"),
    ("sbatch: error: Batch job submission failed: Invalid account or account/partition combination specified",
     "+executor.slurm.sbatch.account=NAME"),
])
def test_sbatch_refusals_name_the_key_and_the_fix(said, words):
    msg = refusal(f"{said}\n", SlurmSettings.of(CONFIG), 1, ["cuda"])
    assert words in msg and "\n" not in msg


def test_the_cells_cpus_are_the_jobs():
    job = {"SLURM_JOB_ID": "17", "SLURM_ARRAY_JOB_ID": "12", "SLURM_ARRAY_TASK_ID": "3", "SLURM_CPUS_PER_TASK": "4",
           "SLURM_JOB_PARTITION": "debug", "SLURMD_NODENAME": "n1", "SLURM_MEM_PER_NODE": "8192",
           "SLURM_RESTART_COUNT": "1"}
    assert job_cpus(job).count == 4 and job_cpus(job).source == "SLURM_CPUS_PER_TASK"
    assert slurm_job(job) == {"job_id": "12_3", "partition": "debug", "node": "n1", "cpus_per_task": 4,
                              "mem_mb": 8192, "gpus": 0, "restarts": 1}
    outside = train_conditions({})
    assert outside["cpus_from"] == "affinity mask" and outside["cpus"] >= 1 and "slurm" not in outside
