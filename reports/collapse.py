"""The footnote of a table row whose runs collapsed (``protocols.collapse`` records
``diagnostics["collapse"]`` in each run's results.json): what happened in which run, and the
likely cause."""

from __future__ import annotations

from typing import Iterable

from protocols.results import RunResult

LABEL = "[collapsed]"


def collapsed_runs(runs: Iterable[RunResult]) -> list[RunResult]:
    """The finished runs among ``runs`` whose diagnostics say they collapsed."""
    return [r for r in runs if r.status == "ok" and ((r.diagnostics or {}).get("collapse") or {}).get("collapsed")]


def collapse_note(runs: list[RunResult]) -> str:
    """One footnote for a row's collapsed runs (at most three named, then a count)."""
    parts = []
    for r in runs[:3]:
        c = r.diagnostics["collapse"]
        parts.append(f"{r.dataset}/{r.scene} seed {r.seed}: {c.get('what', 'collapsed')}; likely cause: "
                     f"{c.get('likely_cause', 'not recorded')}")
    more = f"; and {len(runs) - 3} more run(s)" if len(runs) > 3 else ""
    return (f"{LABEL} = the model collapsed, its metrics are of what was left: " + " | ".join(parts) + more
            + " (results.json diagnostics.collapse, log.txt)")
