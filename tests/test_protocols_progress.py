"""The grid's progress lines where output is no terminal (a log, CI, a pipe): each names the cell
that has just ended and its status, the last one included."""

import re

from protocols.executors import execute


def _cell(payload: dict) -> dict:
    """A stand-in cell (module level: the local executor's workers import it)."""
    return {"key": payload["key"], "status": payload["status"], **payload.get("extra", {})}


PAYLOADS = [{"key": "a/3dgs", "status": "ok"}, {"key": "b/3dgs", "status": "failed"},
            {"key": "c/3dgs", "status": "ok", "extra": {"skipped": True}}]
SAID = {"a/3dgs": "ok", "b/3dgs": "failed", "c/3dgs": "skipped (finished before)"}


def _lines(text: str) -> list[tuple[int, str, str]]:
    out = []
    for line in text.splitlines():
        m = re.fullmatch(r"grid: run (\d+)/3 \(\d+%\), \d+ s, (\S+): (.+)", line)
        if m:
            out.append((int(m[1]), m[2], m[3]))
    return out


def test_each_line_names_the_cell_it_counts(capsys):
    execute(_cell, PAYLOADS, kind="sequential")
    lines = _lines(capsys.readouterr().err)
    assert lines == [(i + 1, p["key"], SAID[p["key"]]) for i, p in enumerate(PAYLOADS)]


def test_parallel_lines_name_every_cell_once(capsys):
    execute(_cell, PAYLOADS, kind="local", workers=2)
    lines = _lines(capsys.readouterr().err)
    assert [n for n, _, _ in lines] == [1, 2, 3]
    assert sorted((k, s) for _, k, s in lines) == sorted(SAID.items())
