"""Report sections and tables as HTML: sortable tables (click a header), the paper's value and Δ
beside ours, bold / italics for best / second, numbered footnotes."""

from __future__ import annotations

from typing import Callable, Iterable, Sequence

from reports.html.escape import esc
from reports.table_model import TIE, Cell, Section, Table


def table_html(table: Table, table_id: str) -> str:
    g = table.grid()
    n_keys = len(table.key_columns)
    out = []
    if table.title:
        out.append(f"<h4>{esc(table.title.lstrip('#').strip())}</h4>")
    head = "".join(f'<th scope="col" class="{"num" if g.numeric[i] else "txt"}" title="sort">{esc(h)}</th>'
                   for i, h in enumerate(g.header))
    body = []
    for cells in g.rows:
        tds = []
        for i, c in enumerate(cells):
            tag = "th" if i == n_keys - 1 and n_keys else "td"
            tds.append(_cell(c, tag, "num" if g.numeric[i] else "txt", table_id))
        body.append("<tr>" + "".join(tds) + "</tr>")
    out.append(plain_table(head, body, table_id))
    if g.notes or g.remarks:
        out.append('<ol class="notes">' + "".join(
            f'<li id="{table_id}-n{i + 1}" value="{i + 1}">{esc(t)}</li>' for i, t in enumerate(g.notes)) + "</ol>")
        out += [f'<p class="note">{esc(n)}</p>' for n in g.remarks]
    return "\n".join(out)


def plain_table(head: str, body: Iterable[str], table_id: str) -> str:
    return (f'<div class="scroll"><table class="sortable" id="{table_id}"><thead><tr>{head}</tr></thead>'
            f'<tbody>{"".join(body)}</tbody></table></div>')


def _cell(c: Cell, tag: str, kind: str, table_id: str) -> str:
    text = esc(c.text)
    if c.rank == 1:
        text = f"<strong>{text}</strong>"
    elif c.rank == 2:
        text = f"<em>{text}</em>"
    elif c.rank == TIE:
        text += " (tie)"
    marks = "".join(f'<sup><a href="#{table_id}-n{_number(m)}">{esc(m)}</a></sup>' for m in c.marks)
    sort = f' data-sort="{c.sort!r}"' if c.sort is not None else ""
    scope = ' scope="row"' if tag == "th" else ""
    return f'<{tag}{scope} class="{kind}"{sort}>{text}{marks}</{tag}>'


def _number(mark: str) -> int:
    return int(mark.translate(str.maketrans("⁰¹²³⁴⁵⁶⁷⁸⁹", "0123456789")))


def section_html(sec: Section, ids: Callable[[str], str], csv_link: Callable[[str], str | None],
                 level: int = 2) -> str:
    """A section: title, intro, tables (or why it is empty), notes, CSV link, sub-sections."""
    out = [f'<h{level} id="{ids(sec.name)}">{esc(sec.title)}</h{level}>']
    out += [f"<p>{esc(p)}</p>" for p in sec.intro]
    if sec.empty_reason:
        out.append(f'<p class="empty">Not produced: {esc(sec.empty_reason)}</p>')
        return "\n".join(out)
    for i, b in enumerate(sec.blocks):
        out.append(table_html(b, ids(f"{sec.name}-t{i}")))
    if sec.notes:
        out.append("<ul>" + "".join(f"<li>{esc(n)}</li>" for n in sec.notes) + "</ul>")
    link = csv_link(sec.name)
    if link and (sec.blocks or sec.records):
        out.append(f'<p class="csv">Machine-readable: <a href="{esc(link)}">{esc(link)}</a></p>')
    for sub in sec.subsections:
        out.append(section_html(sub, ids, csv_link, min(level + 1, 6)))
    return "\n".join(out)


def records_table(records: Sequence[dict], columns: Sequence[str], table_id: str,
                  numeric: Sequence[str] = ()) -> str:
    """A sortable table of plain records (the runs list); numbers sort as numbers."""
    head = "".join(f'<th scope="col" class="{"num" if c in numeric else "txt"}" title="sort">{esc(c)}</th>'
                   for c in columns)
    body = []
    for rec in records:
        tds = []
        for c in columns:
            v = rec.get(c)
            if c in numeric and isinstance(v, (int, float)) and v == v:
                tds.append(f'<td class="num" data-sort="{float(v)!r}">{esc(_short(v))}</td>')
            else:
                tds.append(f'<td class="txt">{esc("" if v is None else v)}</td>')
        body.append("<tr>" + "".join(tds) + "</tr>")
    return plain_table(head, body, table_id)


def _short(v: float) -> str:
    if isinstance(v, int) or float(v).is_integer():
        return f"{int(v)}"
    return f"{v:.4g}"


