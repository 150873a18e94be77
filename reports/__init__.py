"""Reports: run results -> report.md, one CSV per table and PNG plots, the paper's numbers beside ours.

``python -m reports.build RUNS_DIR [--out DIR] [--no-stability]`` or ``reports.build.build_report``.

Modules, one job each: ``runs`` (read a results tree; values with reasons), ``paper`` (the paper's
tables and names), ``table`` (table model: ranking, footnotes, markdown, CSV), ``tables`` (Tables
1–5), ``tradeoff`` + ``plots`` (error against run time), ``diagnostics`` (k_max coverage, learned
α/β/γ), ``stability`` (stiff-case battery), ``environment`` (versions and machines), ``build``.
"""
