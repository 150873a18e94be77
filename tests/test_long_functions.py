"""tools/long_functions.py measures each function from its ``def`` to its last line and names
methods and nested functions by their qualified name."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import long_functions  # noqa: E402


def test_lengths_and_qualified_names(tmp_path):
    for pkg in long_functions.PACKAGES:
        (tmp_path / pkg).mkdir()
    (tmp_path / "smgs" / "m.py").write_text(
        "@decorator\n"
        "def f():\n"
        "    x = 1\n"
        "    return x\n"
        "\n"
        "class C:\n"
        "    def g(self):\n"
        "        def inner():\n"
        "            pass\n"
        "        return inner\n")
    (tmp_path / "reports" / "r.py").write_text("def h(): pass\n")
    got = [(f.lines, f.module, f.name) for f in long_functions.longest(tmp_path, n=3)]
    assert got == [(4, "smgs.m", "C.g"), (3, "smgs.m", "f"), (2, "smgs.m", "C.g.inner")]
    assert str(long_functions.longest(tmp_path, n=5)[-1]) == "    1  reports.r:h"
