"""The report's popping section is shown only beside Table 4 (its rows: tests/test_reports_build.py)."""

from reports.popping import popping_section, wants_popping


def test_without_consistency_runs_it_is_left_out_saying_how_to_build_it():
    assert not wants_popping([])
    sec, plots = popping_section([])
    assert plots == [] and "python -m reports.popping" in sec.empty_reason
