"""The known name nearest a misspelt one, for the messages that refuse an unknown key."""

from __future__ import annotations

import difflib
from collections.abc import Iterable


def did_you_mean(unknown: Iterable[str], known: Iterable[str], where: str = "") -> str:
    """`` (did you mean eval.fps_repeats?)`` for the unknown names with a close known spelling
    (``where``: the section they were given in), else ""."""
    known = sorted(known)
    near = [m[0] for k in sorted(unknown) if (m := difflib.get_close_matches(k, known, n=1, cutoff=0.6))]
    return f" (did you mean {', '.join(f'{where}.{n}' if where else n for n in near)}?)" if near else ""
