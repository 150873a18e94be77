"""The numerical-stability section: the renderer's stiff-case battery against the float64 reference.

Input rows as ``smgs.raster.stability.stiff_battery`` returns them::

    {"case", "mode", "backend", "dtype", "max_abs_err", "max_grad_rel_err",
     "nonfinite_outputs", "nonfinite_grads"}

errors of one backend/dtype against the float64 reference backend on one case and mode
(``max_grad_rel_err`` relative to the largest reference gradient of the same input).
"""

from __future__ import annotations

import math
from collections import defaultdict

from reports.runs import Value, one_line
from reports.table_model import Column, Row, Section, Table, sci

REQUESTED_BACKENDS = ("reference", "cpu")
KEYS = ("case", "mode", "backend", "dtype", "max_abs_err", "max_grad_rel_err", "nonfinite_outputs",
        "nonfinite_grads")


def compute_stability() -> tuple[list[dict] | None, str | None]:
    """Run the battery here: (rows, None) or (None, why not)."""
    try:
        from smgs.raster.stability import stiff_battery
    except Exception as e:  # noqa: BLE001 - any import failure means "not computed", with the reason
        return None, f"smgs.raster.stability is not importable here ({type(e).__name__}: {one_line(str(e))})"
    try:
        return stiff_battery(backends=REQUESTED_BACKENDS, dtypes=("float32",)), None
    except Exception as e:  # noqa: BLE001
        return None, f"stiff_battery raised {type(e).__name__}: {one_line(str(e))}"


def tolerances() -> tuple[float, float] | None:
    try:
        from smgs.raster.stability import GRAD_RTOL, OUT_ATOL
    except Exception:  # noqa: BLE001
        return None
    return float(OUT_ATOL), float(GRAD_RTOL)


def _num(x) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v


def _nonfinite(row: dict) -> list[str]:
    """The hard failures: any non-finite output, gradient or error."""
    why = []
    if (_num(row.get("nonfinite_outputs")) or 0) > 0:
        why.append("non-finite outputs")
    if (_num(row.get("nonfinite_grads")) or 0) > 0:
        why.append("non-finite gradients")
    err, gerr = _num(row.get("max_abs_err")), _num(row.get("max_grad_rel_err"))
    if (err is not None and not math.isfinite(err)) or (gerr is not None and not math.isfinite(gerr)):
        why.append("non-finite error")
    return why


def _over(row: dict, tol: tuple[float, float] | None) -> list[str]:
    """Errors above the battery's nominal tolerances (informative: some cases are ill-conditioned in
    float32 by construction, and the renderer's tests only require them to stay finite)."""
    if not tol:
        return []
    err, gerr = _num(row.get("max_abs_err")), _num(row.get("max_grad_rel_err"))
    why = []
    if err is not None and err > tol[0]:
        why.append(f"output error > {tol[0]:g}")
    if gerr is not None and gerr > tol[1]:
        why.append(f"gradient error > {tol[1]:g}")
    return why


def _flags(row: dict, tol: tuple[float, float] | None) -> list[str]:
    return _nonfinite(row) + _over(row, tol)


def _v(x, what: str) -> Value:
    v = _num(x)
    return Value(v, n=1) if v is not None else Value.absent(f"{what} not in the battery's row")


def stability_section(rows: list[dict] | None, reason: str | None = None, computed_here: bool = False) -> Section:
    sec = Section("stability", "Numerical stability (stiff-case battery)")
    if rows is None:
        sec.empty_reason = f"not computed: {reason or 'no battery rows given'}."
        return sec
    if not rows:
        sec.empty_reason = "the battery returned no rows (no backend available?)."
        return sec
    tol = tolerances()
    sec.intro.append("Each backend and dtype against the float64 reference renderer on the battery's extreme "
                     "inputs (β, γ, α, opacities, identical depths, stacked splats, near-singular conics, …): "
                     "the largest absolute output error (rgb, alpha, depth), the largest gradient error relative "
                     "to the largest reference gradient of the same input, and counts of non-finite values."
                     + (f" Nominal tolerances (smgs.raster.stability): output {tol[0]:g}, gradient {tol[1]:g}; "
                        "cases that are ill-conditioned in float32 by construction (near-singular conics, "
                        "β ≥ 1e3, 50 stacked splats) may exceed them and are only required to stay finite, "
                        "so non-finite values are the failures and \"over nominal\" is information."
                        if tol else ""))
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in rows:
        groups[(str(r.get("mode")), str(r.get("backend")), str(r.get("dtype")))].append(r)
    cols = [Column("max_abs_err", "max |Δ output|", sci), Column("max_grad_rel_err", "max rel. Δ grad", sci),
            Column("nonfinite_outputs", "non-finite outputs", lambda x: f"{x:.0f}"),
            Column("nonfinite_grads", "non-finite grads", lambda x: f"{x:.0f}")]
    summary = []
    for (mode, backend, dtype), rs in sorted(groups.items()):
        def worst(key: str) -> tuple[Value, str]:
            vals = [(_num(r.get(key)), r.get("case")) for r in rs if _num(r.get(key)) is not None]
            if not vals:
                return Value.absent(f"{key} not in the battery's rows"), ""
            x, case = max(vals, key=lambda t: (not math.isfinite(t[0]), t[0]))
            return Value(x, n=len(vals)), str(case)
        err, err_case = worst("max_abs_err")
        gerr, gerr_case = worst("max_grad_rel_err")
        nf_o = sum(_num(r.get("nonfinite_outputs")) or 0 for r in rs)
        nf_g = sum(_num(r.get("nonfinite_grads")) or 0 for r in rs)
        nonfinite = sum(1 for r in rs if _nonfinite(r))
        over = sum(1 for r in rs if _over(r, tol))
        summary.append(Row([mode, backend, dtype], {"max_abs_err": err, "max_grad_rel_err": gerr,
                                                    "nonfinite_outputs": Value(nf_o, n=len(rs)),
                                                    "nonfinite_grads": Value(nf_g, n=len(rs))},
                           info={"cases": str(len(rs)), "worst case (output / grad)": f"{err_case} / {gerr_case}",
                                 "non-finite cases": str(nonfinite),
                                 "over nominal": str(over) if tol else "no tolerance known"}))
    info_cols = ["cases", "worst case (output / grad)", "non-finite cases", "over nominal"]
    sec.blocks.append(Table("Per mode, backend and dtype (worst case over the battery)", ["Mode", "Backend", "dtype"],
                            cols, summary, info_cols, rank="none"))
    failing = [(r, _flags(r, tol)) for r in rows if _flags(r, tol)]
    if failing:
        detail = [Row([str(r.get("case")), str(r.get("mode")), str(r.get("backend")), str(r.get("dtype"))],
                      {c.key: _v(r.get(c.key), c.key) for c in cols}, info={"why": ", ".join(why)})
                  for r, why in failing]
        sec.blocks.append(Table("Cases that are non-finite or over the nominal tolerance", ["Case", "Mode", "Backend",
                                "dtype"], cols, detail, ["why"], rank="none"))
    n_bad = sum(1 for r in rows if _nonfinite(r))
    sec.notes.append(f"{len(rows) - n_bad} of {len(rows)} case × mode × backend × dtype rows are finite"
                     + (f"; {n_bad} have non-finite values." if n_bad else "."))
    if computed_here:
        missing = [b for b in REQUESTED_BACKENDS if b not in {str(r.get('backend')) for r in rows}]
        if missing:
            sec.notes.append(f"Backend(s) not available on this machine, left out: {', '.join(missing)}.")
        sec.notes.append("Computed while building this report, on this machine.")
    sec.records = [{k: r.get(k) for k in KEYS} | {"nonfinite": "; ".join(_nonfinite(r)),
                                                   "over_nominal_tolerance": "; ".join(_over(r, tol))} for r in rows]
    return sec
