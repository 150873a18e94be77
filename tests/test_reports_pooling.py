"""Seeds of one row are pooled only when their configs agree in everything but the seed; a row (and
its paired difference) of seeds trained under different configs says which key differs. A paired
section without a value says why (not "one seed per run" when the seeds are there)."""

from __future__ import annotations

import sys
from pathlib import Path

from protocols.results import read_result, write_result
from reports.build import build_report

sys.path.insert(0, str(Path(__file__).parent))
from reports_tree import make_seed_tree  # noqa: E402
from test_reports_build import section  # noqa: E402

BLOCKS = "procedural/blocks/softmax_gs/full"


def _change(root: Path, run: str, edit) -> None:
    path = root / run / "results.json"
    r = read_result(path)
    edit(r)
    write_result(path.parent, r)


def _lines(md: str, text: str) -> list[str]:
    return [ln for ln in md.splitlines() if text in ln]


def test_a_seed_of_another_step_count_is_not_pooled(tmp_path):
    root = make_seed_tree(tmp_path / "runs")

    def longer(r):
        r.config["protocol"]["steps"] = 400
        r.steps = 400
    _change(root, f"{BLOCKS}/seed1", longer)
    md = build_report(root, stability="x").read_text()
    why = "seeds trained under different configs, not pooled: protocol.steps (seeds 0, 2: 3000; seed 1: 400)"
    t5 = section(md, "Table 5")
    assert why in t5
    assert "31.57" not in md   # the mean of 31.0, 31.9, 31.8 pooled across the two step counts
    paired = t5[t5.index("### Paired differences"):]
    blocks = [ln for ln in paired.splitlines() if ln.startswith("| ") and "blocks" in ln]
    assert len(blocks) == 1 and "| —" in blocks[0] and why in paired
    assert "+1.50 [" not in paired   # the paired difference over the mixed seeds
    assert "| fern |" in paired   # the other scene's pairs agree and are shown


def test_a_seed_of_another_init_opacity_is_named(tmp_path):
    root = make_seed_tree(tmp_path / "runs")
    for seed, opacity in ((0, 0.1), (1, 0.1), (2, 0.5)):
        _change(root, f"{BLOCKS}/seed{seed}",
                lambda r, o=opacity: r.config.update(method={"name": "softmax_gs", "train": {"init_opacity": o}}))
    t5 = section(build_report(root, stability="x").read_text(), "Table 5")
    assert "not pooled: method.train.init_opacity (seeds 0, 1: 0.1; seed 2: 0.5) (rerun them under one config)" in t5
    assert "31.57" not in t5


def test_a_paired_section_without_values_says_why(tmp_path):
    root = make_seed_tree(tmp_path / "runs")

    def failed(r):
        r.status, r.error, r.metrics = "failed", "RuntimeError: out of memory", {}
    for scene, budget in (("procedural/blocks", "full"), ("colmap/fern", "5pct")):
        for seed in range(3):
            _change(root, f"{scene}/3dgs/{budget}/seed{seed}", failed)
    t5 = section(build_report(root, stability="x").read_text(), "Table 5")
    assert "one seed per run" not in t5
    assert "3D GS: failed: RuntimeError: out of memory" in t5[t5.index("Paired differences"):]
