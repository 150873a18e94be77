"""Progress that a terminal and a log file can both hold: a tqdm bar on a TTY, plain whole lines
(no carriage returns, no cursor codes) otherwise, so parallel cells interleave line by line."""

from __future__ import annotations

import sys
import time
from typing import Any, TextIO

from tqdm import tqdm


class LineProgress:
    """The tqdm calls the harness uses, printed as a line at the first step, every tenth of the run
    (at least every ``every_s`` seconds) and at the end."""

    def __init__(self, total: int, desc: str, initial: int = 0, unit: str = "step", stream: TextIO | None = None,
                 every_s: float = 60.0) -> None:
        self.total, self.desc, self.n, self.unit = total, desc, initial, unit
        self.stream = stream or sys.stderr
        self.every_s = every_s
        self.step_every = max(1, total // 10)
        self.start = self.last = time.monotonic()
        self.post = ""
        self.printed = initial

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.monotonic()
        due = self.printed == 0 or self.n // self.step_every > self.printed // self.step_every
        if due or self.n >= self.total or now - self.last >= self.every_s:
            self._line(now)

    def set_postfix(self, post: dict[str, Any] | None = None, **more: Any) -> None:
        self.post = ", ".join(f"{k}={v}" for k, v in {**(post or {}), **more}.items())

    def set_postfix_str(self, text: str) -> None:
        self.post = text

    def _line(self, now: float) -> None:
        pct = f" ({100 * self.n / self.total:.0f}%)" if self.total else ""
        post = f", {self.post}" if self.post else ""
        print(f"{self.desc}: {self.unit} {self.n}/{self.total}{pct}, {now - self.start:.0f} s{post}",
              file=self.stream, flush=True)
        self.printed, self.last = self.n, now

    def close(self) -> None:
        if self.printed != self.n:
            self._line(time.monotonic())


def cell_status(summary: dict[str, Any]) -> str:
    """What a cell's summary stands for, in its progress line and the run's closing count: a cell
    left alone because it finished before is not called ``ok`` as if it had just run."""
    if summary.get("skipped"):
        return "skipped (finished before)"
    if summary.get("busy"):
        return "skipped (another process is writing it)"
    return str(summary["status"])


def progress(total: int, desc: str, initial: int = 0, unit: str = "step", position: int = 0,
             leave: bool = True, disable: bool = False) -> tqdm | LineProgress:
    """A tqdm bar where stderr is a terminal, else :class:`LineProgress` (disabled: a silent one)."""
    if disable:
        return tqdm(total=total, disable=True)
    if sys.stderr.isatty():
        return tqdm(total=total, initial=initial, desc=desc, unit=unit, position=position, leave=leave,
                    dynamic_ncols=True)
    return LineProgress(total, desc, initial, unit)
