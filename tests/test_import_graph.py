"""The layering smgs <- baselines <- protocols <- reports <- smgs_cli holds, inside smgs too
(tools/import_graph.py's SMGS_LAYERS: base helpers, renderer, data, metrics, training, model files,
the package front), and no modules import each other in a circle (every import counted, lazy ones
too)."""

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
    _, wrong, cycles = import_graph.report(tmp_path, smgs_layers=(("smgs", "smgs.a", "smgs.b"),))
    assert wrong == [("protocols.run", "reports.build")]
    assert cycles == [["protocols.run", "reports.build"], ["smgs.a", "smgs.b"]]
    done = subprocess.run([sys.executable, str(ROOT / "tools" / "import_graph.py"), str(tmp_path)],
                          capture_output=True, text=True)
    assert done.returncode == 1
    assert "  protocols.run -> reports.build\n" in done.stdout


def test_inside_smgs_an_import_from_a_lower_group_to_a_higher_one_is_wrong(tmp_path):
    for pkg in [*import_graph.LAYERS, "smgs/raster", "smgs/train"]:
        (tmp_path / pkg).mkdir(exist_ok=True)
        (tmp_path / pkg / "__init__.py").write_text("")
    (tmp_path / "smgs" / "atomic.py").write_text("")
    (tmp_path / "smgs" / "stray.py").write_text("")
    (tmp_path / "smgs" / "raster" / "api.py").write_text("import smgs.atomic\n")
    (tmp_path / "smgs" / "train" / "trainer.py").write_text("from smgs.raster import api\n")
    (tmp_path / "smgs" / "raster" / "cache.py").write_text("def f():\n    from smgs.train.trainer import x\n")
    (tmp_path / "smgs" / "__init__.py").write_text("from smgs.train import trainer\n")
    _, wrong, _ = import_graph.report(tmp_path)
    assert wrong == [("smgs.raster.cache", "smgs.train.trainer"), ("smgs.stray", import_graph.UNPLACED)]
    assert import_graph.group_of("smgs", import_graph.SMGS_LAYERS) == len(import_graph.SMGS_LAYERS) - 1
    assert import_graph.group_of("smgs.raster.csrc", import_graph.SMGS_LAYERS) == 1


def test_imports_by_name_are_edges(tmp_path):
    """A literal module given to importlib.import_module (or __import__) and a "module:attr" string
    naming a module of the harness (the registries' form) are imports; other strings are not."""
    for pkg in import_graph.LAYERS:
        (tmp_path / pkg).mkdir()
        (tmp_path / pkg / "__init__.py").write_text("")
    (tmp_path / "smgs" / "lazy.py").write_text("import importlib\n\ndef f():\n"
                                               "    return importlib.import_module('reports.table')\n")
    (tmp_path / "smgs" / "low.py").write_text("from importlib import import_module\nm = import_module('baselines')\n")
    (tmp_path / "baselines" / "registry.py").write_text('BUILTIN = {"x": "protocols.cell:run_cell"}\n'
                                                        'NOT_OURS = "numpy.linalg:norm"\nTIME = "12:30"\n'
                                                        'DOC = "see baselines.registry:BUILTIN below"\n')
    (tmp_path / "protocols" / "cell.py").write_text("")
    (tmp_path / "reports" / "table.py").write_text("x = __import__('smgs')\n")
    known = import_graph.modules(tmp_path)
    assert import_graph.imports("smgs.lazy", tmp_path / "smgs" / "lazy.py", known) == {"reports.table"}
    assert import_graph.imports("baselines.registry", tmp_path / "baselines" / "registry.py", known) == \
        {"protocols.cell"}
    _, wrong, _ = import_graph.report(tmp_path, smgs_layers=(("smgs", "smgs.lazy", "smgs.low"),))
    assert wrong == [("baselines.registry", "protocols.cell"), ("smgs.lazy", "reports.table"),
                     ("smgs.low", "baselines")]


def test_the_registries_imports_by_name_are_in_the_graph():
    known = import_graph.modules(ROOT)
    assert "baselines.splatting" in import_graph.imports("baselines.registry", known["baselines.registry"], known)
    assert {"smgs.raster.cpu", "smgs.raster.cuda", "smgs.raster.cuda_v2", "smgs.raster.reference"} <= \
        import_graph.imports("smgs.raster.backends", known["smgs.raster.backends"], known)
    assert {"smgs.train.strategies.default", "smgs.train.strategies.mcmc"} <= \
        import_graph.imports("smgs.train.strategies.registry", known["smgs.train.strategies.registry"], known)
