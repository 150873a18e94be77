"""The layering smgs <- baselines <- protocols <- reports holds and no modules import each other in a
circle (tools/import_graph.py, every import counted, lazy ones too)."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import import_graph  # noqa: E402


def test_no_wrong_way_import_and_no_cycle():
    _, wrong, cycles = import_graph.report(ROOT)
    assert wrong == []
    assert cycles == []


def test_the_tool_finds_a_wrong_way_edge_and_a_cycle(tmp_path):
    for pkg in import_graph.LAYERS:
        (tmp_path / pkg).mkdir()
        (tmp_path / pkg / "__init__.py").write_text("")
    (tmp_path / "smgs" / "a.py").write_text("def f():\n    from smgs.b import g\n")
    (tmp_path / "smgs" / "b.py").write_text("from smgs import a\ng = 1\n")
    (tmp_path / "protocols" / "run.py").write_text("import reports.build\n")
    (tmp_path / "reports" / "build.py").write_text("from ..protocols import run\n")
    _, wrong, cycles = import_graph.report(tmp_path)
    assert wrong == [("protocols.run", "reports.build")]
    assert cycles == [["protocols.run", "reports.build"], ["smgs.a", "smgs.b"]]
    done = subprocess.run([sys.executable, str(ROOT / "tools" / "import_graph.py"), str(tmp_path)],
                          capture_output=True, text=True)
    assert done.returncode == 1
    assert "  protocols.run -> reports.build\n" in done.stdout
