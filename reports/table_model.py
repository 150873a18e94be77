"""A results table: our value, the paper's value and their difference per column, best in bold,
second in italics, every "—" with a footnote. Rendered to markdown and to long-format CSV rows.

Comparison columns: ``diff`` prints ours − paper (PSNR, SSIM, LPIPS, MSE, FLIP, %); ``ratio``
prints ours / paper as ×r (counts, minutes, FPS: quantities compared by scale); ``paper`` prints the
paper's value beside ours and no difference (paired differences: ours and the paper's are both A − B).

A table of seed means (``seeds=True``) prints ± sd where a value has two or more seeds, notes n (and
footnotes a value with another n), or says that one seed gives no spread; best / second are only
marked where the lead is larger than the spread, and a lead inside it is a tie (docs/reports.md).
"""

from __future__ import annotations

import html
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable, Literal

from reports.aggregate import TIE, Rank, ranks
from reports.runs import Value

SUPERSCRIPT = str.maketrans("0123456789", "⁰¹²³⁴⁵⁶⁷⁸⁹")
DASH = "—"
RESOLVED = "✱"         # after an interval that excludes 0
SEEDS_GUIDE = ("Values are means over seeds; with two or more seeds ± is their standard deviation (n in the note "
               "under each table; a dataset mean's ± is propagated from its scenes'), and best / second need a lead "
               "larger than that spread, a lead inside it is marked (tie). The paired differences under Tables 1, 2, "
               "4 and 5 give A − B seed by seed with its 95 % Student t interval, ✱ where the interval excludes 0.")
ONE_SEED_NOTE = ("One seed per value: no spread available (more seeds: grid.seeds=[0,1,2] or seeds=3; "
                 "docs/reports.md).")


# ---- number formats ---------------------------------------------------------------------------

def fixed(decimals: int) -> Callable[[float], str]:
    return lambda x: f"{x:.{decimals}f}"


def count(x: float) -> str:
    """Gaussian counts as the paper prints them: 4, 1024, 104K, 2593K."""
    return f"{x:.0f}" if abs(x) < 10_000 else f"{x / 1000:.0f}K"


def sig(x: float) -> str:
    return f"{x:.3g}"


def sci(x: float) -> str:
    return f"{x:.1e}"


def ratio_text(r: float) -> str:
    """×1.25, ×0.93, ×0.0012, ×150."""
    if abs(r) >= 100:
        return f"×{r:.0f}"
    return f"×{r:.2f}" if abs(r) >= 0.1 else f"×{r:.2g}"


def percent(x: float) -> str:
    return f"{100 * x:.1f}%"


# ---- model ------------------------------------------------------------------------------------

@dataclass
class Column:
    """A value column; with ``compare`` it is followed by a paper column and a Δ (or ×) column."""

    key: str
    label: str
    fmt: Callable[[float], str]
    better: Literal["higher", "lower"] | None = None
    compare: Literal["diff", "ratio", "paper"] | None = None
    decimals: int = 2          # of the Δ column
    show_std: bool = False
    group: str = ""            # row-wise ranking: columns of the same group compete
    delta_fmt: Callable[[float], str] | None = None

    def value_text(self, v: Value, std: bool) -> str:
        """The cell text of a value: mean, "± sd" (when shown and there is one), "[low, high]✱" (an
        interval, marked when it excludes 0)."""
        text = self.fmt(v.mean)
        if std and v.std is not None:
            text += f" ± {self.fmt(v.std)}"
        if v.ci is not None:
            lo, hi = v.ci
            text += f" [{self.fmt(lo)}, {self.fmt(hi)}]" + (RESOLVED if lo > 0 or hi < 0 else "")
        return text

    def delta_text(self, ours: float, paper: float) -> str:
        if self.compare == "ratio":
            return ratio_text(ours / paper) if paper else ""
        d = ours - paper
        return self.delta_fmt(d) if self.delta_fmt else f"{d:+.{self.decimals}f}"


@dataclass
class Row:
    keys: list[str]                                       # key-column cells (display text)
    values: dict[str, Value]                              # column key -> ours
    paper: dict[str, Value] = field(default_factory=dict)  # column key -> the paper's
    rank_group: tuple = ()                                # rows that compete (column ranking)
    label_notes: list[str] = field(default_factory=list)  # footnotes on the row's label (last key cell)
    no_compare: dict[str, str] = field(default_factory=dict)  # column key -> why no Δ
    info: dict[str, str] = field(default_factory=dict)    # plain text columns (device, flow)
    csv: dict[str, object] = field(default_factory=dict)  # machine identity fields for the CSV


@dataclass
class Table:
    """One markdown table (a block of a section)."""

    title: str
    key_columns: list[str]
    columns: list[Column]
    rows: list[Row]
    info_columns: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    rank: Literal["column", "row", "none"] = "column"
    seeds: bool = False        # values are means over seeds: ± sd, n, the spread-aware ranking's note

    # -- ranking ----------------------------------------------------------------------------
    def ranks(self) -> dict[tuple[int, str], Rank]:
        """(row index, column key) -> 1 (best), 2 (second) or "tie", among competing cells with a value
        (``reports.aggregate.ranks``): by column, the rows of one ``rank_group``; by row, the columns of
        one ``group``."""
        cands = []
        for i, r in enumerate(self.rows):
            for c in self.columns:
                v = r.values.get(c.key)
                if self.rank == "none" or not c.better or v is None or not v.ok:
                    continue
                competing = (c.key, r.rank_group) if self.rank == "column" else (i, c.group)
                cands.append((competing, (i, c.key), v.mean, c.fmt(v.mean), v.std, c.better == "higher"))
        return ranks(cands)

    # -- seeds ------------------------------------------------------------------------------
    def seed_count(self) -> int:
        """The most common number of seeds behind this table's values (0: no value)."""
        ns = Counter(v.n for r in self.rows for c in self.columns for v in [r.values.get(c.key)]
                     if v is not None and v.ok)
        return ns.most_common(1)[0][0] if ns else 0

    def spread_note(self) -> str | None:
        """What ± means here and the seeds behind it, or that one seed gives no spread (seed tables)."""
        if not self.seeds:
            return None
        n = self.seed_count()
        if n == 0:
            return None
        if max(v.n for r in self.rows for v in r.values.values() if v.ok) < 2:
            return ONE_SEED_NOTE
        note = f"± is the standard deviation over seeds (n = {n} per value unless a footnote says otherwise)"
        if self.rank == "none":
            return note + "."
        return note + ("; best / second are marked only where the lead is larger than that spread, a lead inside "
                       "it is a tie.")

    # -- cells (shared by markdown and HTML) -------------------------------------------------
    def grid(self) -> "Grid":
        """Header, cells and footnotes as every renderer shows them."""
        notes = Footnotes()
        ranks = self.ranks()
        n_mode = self.seed_count() if self.seeds else 0
        spread = self.seeds and any(v.n >= 2 for r in self.rows for v in r.values.values() if v.ok)
        header = list(self.key_columns)
        numeric = [False] * len(header)
        for c in self.columns:
            header.append(c.label)
            if c.compare:
                header += ["paper"] + ([] if c.compare == "paper" else ["×paper" if c.compare == "ratio" else "Δ"])
            numeric += [True] * (1 + (c.compare is not None) + (c.compare in ("diff", "ratio")))
        header += self.info_columns
        numeric += [False] * len(self.info_columns)
        rows = []
        for i, row in enumerate(self.rows):
            cells = [Cell(k) for k in row.keys]
            if cells:  # the row's label is its last key cell
                cells[-1].marks = [notes.mark(n) for n in row.label_notes]
            for c in self.columns:
                v = row.values.get(c.key, Value.absent("no result in the runs directory"))
                cell = _value_cell(v, c, ranks.get((i, c.key)), notes, c.show_std or self.seeds)
                if spread and v.ok and v.n != n_mode and not any(n.startswith(f"{v.n} of ") for n in v.notes):
                    cell.marks.append(notes.mark(f"{v.n} seed{'s' if v.n != 1 else ''}"))
                cells.append(cell)
                if c.compare:
                    p = row.paper.get(c.key, Value.absent("not in the paper"))
                    cells.append(_value_cell(p, Column(c.key, "", c.fmt), None, notes, False))
                    if c.compare == "paper":
                        continue
                    if c.key in row.no_compare:
                        cells.append(Cell("n/c", marks=[notes.mark(row.no_compare[c.key])]))
                    elif v.ok and p.ok:
                        cells.append(Cell(c.delta_text(v.mean, p.mean),
                                          sort=v.mean / p.mean if c.compare == "ratio" and p.mean else v.mean - p.mean))
                    else:
                        cells.append(Cell(""))
            cells += [Cell(row.info.get(k, "")) for k in self.info_columns]
            rows.append(cells)
        remarks = list(self.notes)
        note = self.spread_note()
        if note:
            remarks.insert(0, note)
        return Grid(header, numeric, rows, notes.texts, remarks)

    # -- markdown ---------------------------------------------------------------------------
    def markdown(self) -> str:
        g = self.grid()
        n_keys = len(self.key_columns)
        align = [":--" if i < n_keys or not g.numeric[i] else "--:" for i in range(len(g.header))]
        lines = ["| " + " | ".join(md_text(h) for h in g.header) + " |", "|" + "|".join(align) + "|"]
        for cells in g.rows:
            lines.append("| " + " | ".join(md_text(c.markdown()) for c in cells) + " |")
        out = []
        if self.title:
            out.append(f"**{md_text(self.title)}**")   # titles hold recorded names (datasets, patterns)
            out.append("")
        out += lines
        foot = [f"{superscript(i + 1)} {md_text(t)}  " for i, t in enumerate(g.notes)]
        if foot or g.remarks:
            out.append("")
        out += foot
        out += [f"- {md_text(n)}" for n in g.remarks]
        return "\n".join(out)

    # -- CSV --------------------------------------------------------------------------------
    def records(self) -> list[dict[str, object]]:
        """Long-format rows: identity fields, then per column value, std, n, paper, Δ / ratio,
        rank (1 best, 2 second) and note (the reason for an absent value, or notes)."""
        ranks = self.ranks()
        recs = []
        for i, row in enumerate(self.rows):
            rec: dict[str, object] = dict(row.csv)
            for c in self.columns:
                v = row.values.get(c.key, Value.absent("no result in the runs directory"))
                rec[c.key] = v.mean if v.ok else None
                if c.show_std or self.seeds or v.ci is not None:
                    rec[f"{c.key}_std"] = v.std
                rec[f"{c.key}_n"] = v.n if v.ok else 0
                if v.ci is not None:
                    rec[f"{c.key}_ci_low"], rec[f"{c.key}_ci_high"] = v.ci
                    rec[f"{c.key}_excludes_0"] = int(v.ci[0] > 0 or v.ci[1] < 0)
                if c.compare == "paper" and v.seeds:  # paired differences: each seed's, to check by hand
                    rec[f"{c.key}_per_seed"] = ";".join(f"{seed}:{x:.6g}" for seed, x in v.seeds)
                if c.compare:
                    p = row.paper.get(c.key, Value.absent("not in the paper"))
                    rec[f"paper_{c.key}"] = p.mean if p.ok else None
                if c.compare in ("diff", "ratio"):
                    comparable = v.ok and p.ok and c.key not in row.no_compare and (c.compare != "ratio" or p.mean)
                    name = f"ratio_{c.key}" if c.compare == "ratio" else f"delta_{c.key}"
                    rec[name] = (v.mean / p.mean if c.compare == "ratio" else v.mean - p.mean) if comparable else None
                if c.better:
                    rec[f"{c.key}_rank"] = ranks.get((i, c.key))
                rec[f"{c.key}_note"] = "; ".join(([v.reason] if v.reason else []) + list(v.notes)
                                                 + ([row.no_compare[c.key]] if c.key in row.no_compare else []))
            for k in self.info_columns:
                rec[k.lower().replace(" ", "_")] = row.info.get(k, "")
            rec["row_notes"] = "; ".join(row.label_notes)
            recs.append(rec)
        return recs


@dataclass
class Cell:
    """One table cell: display text, rank (1 best, 2 second: bold / italics), footnote marks and the
    number it sorts by (None: sort by text)."""

    text: str
    rank: Rank | None = None
    marks: list[str] = field(default_factory=list)
    sort: float | None = None

    def markdown(self) -> str:
        text = self.text
        if self.rank == 1:
            text = f"**{text}**"
        elif self.rank == 2:
            text = f"*{text}*"
        elif self.rank == TIE:
            text += " (tie)"
        return text + "".join(self.marks)


@dataclass
class Grid:
    header: list[str]
    numeric: list[bool]        # per column: numbers (right-aligned)
    rows: list[list[Cell]]
    notes: list[str]           # footnote texts, numbered from 1
    remarks: list[str] = field(default_factory=list)   # the table's notes below its footnotes


def superscript(n: int) -> str:
    return str(n).translate(SUPERSCRIPT)


def _value_cell(v: Value, c: Column, rank: Rank | None, notes: "Footnotes", std: bool) -> Cell:
    if not v.ok:
        return Cell(DASH, marks=[notes.mark(v.reason or "no value")])
    return Cell(c.value_text(v, std), rank, [notes.mark(n) for n in v.notes], v.mean)


def md_text(text: object) -> str:
    """Text for one line of report.md, inert: HTML escaped (an error message or a config value is
    data, never markup), table pipes escaped, no link target, one line."""
    s = html.escape(" ".join(str(text).split()), quote=False)
    return s.replace("|", "\\|").replace("](", "]\\(")


class Footnotes:
    """Numbered notes of one table; the same text gets the same number."""

    def __init__(self) -> None:
        self.texts: list[str] = []

    def mark(self, text: str) -> str:
        if text not in self.texts:
            self.texts.append(text)
        return superscript(self.texts.index(text) + 1)


@dataclass
class Section:
    """A report section that is one paper table: markdown blocks and one CSV (sub-sections have their own)."""

    name: str                   # CSV file stem, e.g. "table2_realworld"
    title: str
    intro: list[str] = field(default_factory=list)
    blocks: list[Table] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    records: list[dict[str, object]] | None = None   # CSV rows; default: the blocks' records
    empty_reason: str | None = None                  # why nothing could be tabulated
    subsections: list["Section"] = field(default_factory=list)

    def csv_records(self) -> list[dict[str, object]]:
        if self.records is not None:
            return self.records
        return [rec for b in self.blocks for rec in b.records()]

    def all(self) -> list["Section"]:
        """This section and its sub-sections, depth first (one CSV each)."""
        return [self] + [s for sub in self.subsections for s in sub.all()]

    def markdown(self, level: int = 2, link: Callable[[str], str | None] = lambda name: None) -> str:
        out = [f"{'#' * level} {md_text(self.title)}", ""]
        out += [md_text(p) + "\n" for p in self.intro]
        if self.empty_reason:
            out += [f"Not produced: {md_text(self.empty_reason)}", ""]
            return "\n".join(out)
        for b in self.blocks:
            out += [b.markdown(), ""]
        out += [f"- {md_text(n)}" for n in self.notes]
        csv_link = link(self.name)
        if csv_link and (self.blocks or self.records):
            out += ["", f"Machine-readable: [{csv_link}]({csv_link})"]
        for sub in self.subsections:
            out += ["", sub.markdown(level + 1, link)]
        return "\n".join(out).rstrip() + "\n"
