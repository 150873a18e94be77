"""Text into HTML, data into a page: every string from configs, paths and errors goes through here."""

from __future__ import annotations

import html
import json
import math
import os
from pathlib import Path
from urllib.parse import quote


def esc(text: object) -> str:
    """Text content or attribute value: & < > " ' become entities, so a run named <script> stays text."""
    return html.escape(str(text), quote=True)


def clean(x: object) -> object:
    """JSON-safe data: non-finite floats become null (JSON has no NaN), tuples become lists."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {str(k): clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [clean(v) for v in x]
    return x


def script_json(data: object) -> str:
    """JSON for a <script type="application/json"> element: no "</script>", "<!--" or line separators
    can end or alter the element, whatever the strings hold (they are escaped as \\uXXXX)."""
    text = json.dumps(clean(data), ensure_ascii=False, allow_nan=False, separators=(",", ":"))
    for ch in ("<", ">", "&", "\u2028", "\u2029"):
        text = text.replace(ch, f"\\u{ord(ch):04x}")
    return text


def plotly_text(text: object) -> str:
    """A string Plotly draws (legend, hover, title): Plotly reads a subset of HTML tags in its text and
    decodes entities, so escaping keeps <b> or <script> in a run name literal."""
    return html.escape(str(text), quote=False)


def rel_url(target: Path, base: Path) -> str:
    """``target`` as a relative URL from the directory ``base`` (each path segment percent-encoded, so
    '#', '?', '%' or spaces in run names stay part of the path)."""
    rel = os.path.relpath(Path(target).resolve(), Path(base).resolve())
    return "/".join(quote(part) for part in Path(rel).parts)
