"""The install story holds together: the torch that CI and the README install first is inside the
package's torch range (so pip keeps it), the torch running these tests is too, and CI runs the
README's test command."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import torch
from packaging.requirements import Requirement
from packaging.version import Version

REPO = Path(__file__).resolve().parent.parent


def torch_requirement() -> Requirement:
    deps = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    (req,) = [Requirement(d) for d in deps if Requirement(d).name == "torch"]
    return req


def readme_commands() -> list[str]:
    block = re.search(r"```bash\n(.*?)```", (REPO / "README.md").read_text(), re.S).group(1)
    return [ln for ln in block.splitlines() if ln and not ln.startswith("#")]


def test_torch_is_a_range_that_admits_what_is_installed_first():
    spec = torch_requirement().specifier
    assert not any(s.operator == "==" for s in spec), "a pin would make pip replace a user's own torch build"
    pinned = {m for text in ((REPO / ".ci" / "run").read_text(), (REPO / "README.md").read_text())
              for m in re.findall(r"pip install torch==([\d.]+)", text)}
    assert pinned and all(Version(v) in spec for v in pinned)
    assert Version(torch.__version__.split("+")[0]) in spec
    assert Version("2.11.0") in spec and Version("2.10.0") not in spec  # the oldest release the code ran on


def test_the_readme_opens_with_the_two_commands_and_ci_runs_its_test_command():
    main, tests = readme_commands()
    assert main.startswith("pip install torch==") and "-e ." in main and main.endswith("smgs run +experiment=smoke")
    assert tests.startswith("pip install torch==") and '-e ".[test]"' in tests
    test_command = tests.split("&&")[-1].strip()
    ci = (REPO / ".ci" / "run").read_text().splitlines()
    assert test_command == "python -m pytest" and test_command in ci
