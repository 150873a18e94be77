"""The commands of the documentation, as tests/test_docs_commands.py runs them: collected from the
fenced ```bash blocks of README.md and docs/**/*.md, made to run here on the project's small scenes
(the substitution rule below), and run in one child process.

Substitution rule (what a documented command needs that a reader has and this machine has not):
- ``dataset.path=P`` (also ``+dataset.path=``): P itself where it exists (a relative P from the
  repository root, as the results pages were run from the checkout); otherwise P is a placeholder
  for the reader's own scene (``/my/capture``) and becomes a link of the same name in the test's
  folder (so the scene keeps the name the page gives it) to the project's fixture scene of that
  kind: fern (../shared/data/fern) for ``dataset=colmap``, fox for ``dataset=transforms``.
- a model to score (``smgs evaluate point_cloud.ply``, ``model.ply``) that is not there: the model
  of the smoke run's ``3dgs`` cell, written by ``smgs export`` first.
- a training or scoring command (``smgs run``, ``smgs evaluate`` and their ``python -m`` forms) gets
  ``SHORT`` appended: a short run (docs/usage.md, "Short runs"), the same for every command, so that
  commands that differ only in their step count share their runs.
Every command runs in one folder (``runs/`` lands there), in the order of the pages (README.md
first, then docs/ by name), commands that make runs before those that read them (``PHASES``).
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DATA = REPO.parent / "shared" / "data"
SCENES = {"colmap": DATA / "fern", "transforms": DATA / "fox"}
PAGES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
BLOCK = re.compile(r"^```bash\n(.*?)^```", re.S | re.M)

SHORT = ("protocol=cpu", "protocol.steps=2", "protocol.schedule_steps=null", "++protocol.max_width=64",
         "eval.fps_repeats=1", "eval.fps_warmup=0", "++method.train.gaussians.n_random=1000")
"""The short run: the CPU preset at 2 steps on images at most 64 px wide, FPS timed once, 1000
random initial points for a scene without SfM points (fox): seconds per run instead of minutes."""
TRAINS = ("run", "evaluate")   # the smgs commands that get SHORT
PHASES = {"run": 0, "evaluate": 0, "rm": 2}
"""When a command runs, by its verb: those that make runs first, those that remove them last; every
other command (export, report, ...) in between, in the order of the pages. A command never runs
before one above it in its block (``rm`` then ``smgs report``: the report without them)."""
SMOKE_CELL = "runs/smoke/procedural/blocks/3dgs/full/seed0"


@dataclass(frozen=True)
class DocCommand:
    page: str            # README.md, docs/usage.md, ...
    line: int
    text: str            # the command as written, without its comment, whitespace collapsed
    env: tuple[tuple[str, str], ...] = ()   # what an ``export`` earlier in its block set
    block: int = 0       # the line its block starts at

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}"


def _without_comment(line: str) -> str:
    """``line`` up to a ``#`` that starts a shell comment (after blank, outside quotes)."""
    quote = None
    for i, c in enumerate(line):
        if quote:
            quote = None if c == quote else quote
        elif c in "'\"":
            quote = c
        elif c == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i]
    return line


def _segments(line: str) -> list[str]:
    """The commands of ``a && b``, each with its whitespace collapsed."""
    return [" ".join(part.split()) for part in re.split(r"\s&&\s", line) if part.strip()]


def collect() -> list[DocCommand]:
    """Every command of every ```bash block of the pages, in order."""
    out = []
    for page in PAGES:
        text = page.read_text()
        for block in BLOCK.finditer(text):
            first = text[:block.start(1)].count("\n") + 1
            env: dict[str, str] = {}
            joined, start = "", 0
            for i, raw in enumerate(block.group(1).splitlines()):
                if not joined:
                    start = first + i
                line = _without_comment(raw).rstrip()
                if line.endswith("\\"):
                    joined += line[:-1] + " "
                    continue
                joined += line
                for seg in _segments(joined):
                    out.append(DocCommand(str(page.relative_to(REPO)), start, seg, tuple(env.items()), first))
                    m = re.fullmatch(r"export (\w+)=(\S+)", seg)
                    if m:
                        env[m.group(1)] = m.group(2)
                joined = ""
    return out


def module_commands() -> dict[str, str]:
    """``python -m MODULE`` -> the smgs command that fronts it (the command table's "(python -m X)")."""
    from smgs_cli.main import COMMANDS

    return {m.group(1): c.name for c in COMMANDS if (m := re.search(r"\(python -m ([\w.]+)\)", c.help))}


@dataclass
class Job:
    """One thing the child runs: an smgs command in its process (``argv``) or a shell command."""

    argv: list[str] | None = None
    shell: str | None = None
    env: dict[str, str] = field(default_factory=dict)

    def key(self) -> str:
        return json.dumps([self.argv, self.shell, sorted(self.env.items())])


def _scene(value: str, kind: str | None, work: Path) -> str:
    """A ``dataset.path`` value under the substitution rule (see the module's doc)."""
    given = Path(value)
    here = given if given.is_absolute() else REPO / given
    if here.exists():
        return str(here.resolve())
    if kind not in SCENES:
        return value
    link = work / "scenes" / value.lstrip("/")
    if not link.exists():
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to(SCENES[kind], target_is_directory=True)
    return str(link)


def _is_short(arg: str) -> bool:
    """Whether ``arg`` sets a key that SHORT sets (SHORT's value wins, so it is left out)."""
    return arg.lstrip("+").split("=", 1)[0] in {s.lstrip("+").split("=", 1)[0] for s in SHORT}


def plan(cmd: DocCommand, work: Path) -> list[Job]:
    """The jobs that run ``cmd`` here (more than one where a placeholder model must be made first)."""
    tokens = shlex.split(cmd.text)
    env = dict(cmd.env)
    if tokens[:2] == ["python", "-m"] and tokens[2] in module_commands():
        tokens = ["smgs", module_commands()[tokens[2]], *tokens[3:]]
    if tokens[0] != "smgs":
        return [Job(shell=cmd.text, env=env)]
    argv = tokens[1:]
    kind = next((a.split("=", 1)[1] for a in argv if a.startswith("dataset=")), None)
    argv = [f"{a.split('=', 1)[0]}={_scene(a.split('=', 1)[1], kind, work)}"
            if a.lstrip("+").startswith("dataset.path=") else a for a in argv]
    jobs = []
    if argv[0] == "evaluate":
        model = next((a for a in argv[1:] if a.endswith(".ply")), None)
        if model and not (work / model).exists():
            jobs += [Job(["run", "+experiment=smoke", *SHORT], env=env),
                     Job(["export", SMOKE_CELL, "--out", str(work / "model.ply")], env=env)]
            argv = [str(work / "model.ply") if a == model else a for a in argv]
    if argv[0] in TRAINS:
        argv = [argv[0], *[a for a in argv[1:] if not _is_short(a)], *SHORT]
    return jobs + [Job(argv, env=env)]


def order(commands: list[DocCommand]) -> list[DocCommand]:
    """``commands`` in the order they run (``PHASES``), the pages' order within a phase."""
    phases, reached = [], {}
    for c in commands:
        key = (c.page, c.block)
        reached[key] = max(reached.get(key, 0), phase(c))
        phases.append(reached[key])
    return [c for _, _, c in sorted(zip(phases, range(len(commands)), commands), key=lambda x: x[:2])]


def phase(cmd: DocCommand) -> int:
    tokens = shlex.split(cmd.text)
    verb = tokens[1] if tokens[0] == "smgs" and len(tokens) > 1 else tokens[0]
    if tokens[:2] == ["python", "-m"] and len(tokens) > 2:
        verb = module_commands().get(tokens[2], tokens[2])
    return PHASES.get(verb, 1)


def _run_job(job: dict, log: Path) -> int:
    """Run one job with its output to ``log`` (file descriptors 1 and 2, so children's output too)."""
    from smgs_cli.main import main

    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    env = dict(os.environ)
    os.environ.update(job["env"])
    with open(log, "w") as f:
        os.dup2(f.fileno(), 1)
        os.dup2(f.fileno(), 2)
        try:
            if job["shell"] is not None:
                return subprocess.run(["bash", "-c", job["shell"]]).returncode
            try:
                return int(main(job["argv"]) or 0)
            except SystemExit as e:
                return e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        except Exception:   # noqa: BLE001 (a traceback is the command's failure; the log has it)
            import traceback

            traceback.print_exc()
            return 1
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.environ.clear()
            os.environ.update(env)


def child(work: Path) -> None:
    """Run the jobs of ``work/jobs.json`` in order, in ``work``; write each one's exit status and
    seconds to ``work/status.json`` as it ends."""
    os.chdir(work)
    jobs = json.loads((work / "jobs.json").read_text())
    status: dict[str, list] = {}
    (work / "logs").mkdir(exist_ok=True)
    for i, job in enumerate(jobs):
        start = time.monotonic()
        rc = _run_job(job, work / "logs" / f"{i}.log")
        status[str(i)] = [rc, round(time.monotonic() - start, 1)]
        (work / "status.json").write_text(json.dumps(status))


if __name__ == "__main__":
    child(Path(sys.argv[1]))
