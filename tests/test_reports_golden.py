"""The report's numbers and footnotes do not change when its computation does: every table CSV and
report.md of the fixture run trees (tests/report_golden.py) equal the golden files written at 9235246,
before the report was computed from the results DataFrame (CSV numbers to 1e-9 relative: a sum in
another order may move the last bit; report.md exactly)."""

from __future__ import annotations

import difflib
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import report_golden  # noqa: E402


@pytest.mark.parametrize("case", list(report_golden.CASES))
def test_report_equals_the_golden_files(case, tmp_path):
    got = report_golden.build(case, tmp_path)
    want_dir = report_golden.GOLDEN / case
    want = {p.relative_to(want_dir).as_posix(): p.read_text() for p in sorted(want_dir.rglob("*")) if p.is_file()}
    assert sorted(got) == sorted(want), "the set of CSVs differs"
    problems = []
    for name, text in want.items():
        if name.endswith(".csv"):
            problems += [f"{name}: {d}" for d in report_golden.csv_differences(text, got[name])]
        elif text != got[name]:
            diff = difflib.unified_diff(text.splitlines(), got[name].splitlines(), "golden", "now", lineterm="", n=1)
            problems.append(f"{name}:\n" + "\n".join(list(diff)[:40]))
    assert not problems, "\n".join(problems[:20])


def test_the_comparison_sees_a_changed_number_and_a_changed_header():
    want = "a,b\nx,1.5\n"
    assert report_golden.csv_differences(want, "a,b\nx,1.5000000000001\n") == []
    assert report_golden.csv_differences(want, "a,b\nx,1.51\n") == ["row 1 b: '1.5' != '1.51'"]
    assert report_golden.csv_differences(want, "a,c\nx,1.5\n")[0].startswith("header")
    assert report_golden.csv_differences(want, "a,b\ny,1.5\n") == ["row 1 a: 'x' != 'y'"]
