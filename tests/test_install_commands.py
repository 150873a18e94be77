"""The install story holds together: the torch that CI and the README install first is inside the
package's torch range (so pip keeps it), the torch running these tests is too, CI runs the
README's test command, and the CPU-only install names the same torch from PyTorch's CPU index."""

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
    """The first block holds on a machine without a GPU: its torch is PyTorch's CPU build."""
    main, tests = readme_commands()
    assert main.startswith("pip install torch==") and "--index-url https://download.pytorch.org/whl/cpu" in main
    assert "-e ." in main and main.endswith("smgs run +experiment=smoke")
    assert '-e ".[test]"' in tests and "torch" not in tests   # the torch of the first command is kept
    test_command = tests.split("&&")[-1].strip()
    ci = (REPO / ".ci" / "run").read_text().splitlines()
    assert test_command == "python -m pytest" and test_command in ci


def test_the_cpu_only_install_takes_the_same_torch_from_pytorchs_cpu_index():
    """PyPI's torch on Linux x86-64 is the CUDA build; the README and docs/usage.md give a CPU-only
    machine the same release from PyTorch's CPU wheel index, and the README's GPU line takes PyPI's
    build, then the same harness install."""
    main, _ = readme_commands()
    pin = re.search(r"torch==([\d.]+)", main)[1]
    for page in (REPO / "README.md", REPO / "docs" / "usage.md"):
        found = re.findall(r"pip install torch==([\d.]+) --index-url (\S+)", page.read_text())
        assert found and set(found) == {(pin, "https://download.pytorch.org/whl/cpu")}, page
    gpu_line = next(ln for ln in (REPO / "README.md").read_text().splitlines()
                    if ln.startswith(f"pip install torch=={pin} &&"))
    assert gpu_line.split("&&", 1)[1].strip() == main.split("&&", 1)[1].strip()   # then the same steps
