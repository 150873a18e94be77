"""The runner's last step builds the report by a call in its own process, through the function the
config names (protocols sit below reports, so the runner imports no report code)."""

from pathlib import Path

import pytest

import reports.build
from protocols.report_step import ReportFailed, build_report, builder

CALLS: list[Path] = []


def record(runs_dir: Path) -> Path:
    CALLS.append(runs_dir)
    return runs_dir / "report" / "report.md"


def test_the_configured_builder_is_the_report_builder_and_the_config_its_one_home():
    """configs/config.yaml names the builder; protocols/ names no report code (tools/import_graph.py
    sees a "module:function" string as an import), so unset is an error saying where it is set."""
    from hydra import compose, initialize_config_dir

    from protocols.run import CONFIG_DIR

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        assert builder(compose(config_name="config").report_builder) is reports.build.build_report
    with pytest.raises(ValueError, match="report_builder is not set.*configs/config.yaml.*report=false"):
        builder(None)


def test_the_named_builder_is_called_in_this_process(tmp_path):
    CALLS.clear()
    assert build_report(tmp_path, f"{__name__}:record") == tmp_path / "report" / "report.md"
    assert CALLS == [tmp_path]


@pytest.mark.parametrize("spec, words", [("reports.build", "expected module:function"),
                                         ("reports.nothing:build", "names no function"),
                                         ("reports.build:no_such_function", "names no function"),
                                         ("reports.build:DEFAULT_THAT_IS_NOT_CALLABLE", "names no function")])
def test_a_spec_that_names_no_function_says_what_to_write(spec, words):
    with pytest.raises(ValueError, match=words):
        builder(spec)


def fail(runs_dir: Path) -> Path:
    raise OSError(28, "No space left on device")


def test_the_builders_error_is_one_line_that_says_the_runs_are_kept(tmp_path):
    with pytest.raises(ReportFailed, match=r"^the report step failed \(OSError: .*No space left on device\); "
                                           r"the runs are recorded, rebuild the report with `smgs report "):
        build_report(tmp_path, f"{__name__}:fail")


def test_a_bad_builder_stops_the_sweep_before_anything_runs(tmp_path):
    from protocols.run import run_experiment

    with pytest.raises(SystemExit, match="invalid config, nothing was run: report_builder='nowhere:x'"):
        run_experiment(["+experiment=smoke", f"out_dir={tmp_path}", "report_builder=nowhere:x"])
    assert not any(tmp_path.iterdir())


def test_a_sweep_calls_the_configured_builder(tmp_path):
    from protocols.run import run_experiment

    CALLS.clear()
    run_experiment(["+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]", "grid.scenes=[circle4]",
                    "grid.methods=[3dgs]", "dataset.size=16", "dataset.steps=4", "eval.fps_repeats=1",
                    "eval.flip=false", f"out_dir={tmp_path}", f"report_builder={__name__}:record"])
    assert CALLS == [tmp_path]
