"""Reports: run results -> report.md, one CSV per table and PNG plots, the paper's numbers beside ours.

``python -m reports.build RUNS_DIR [--out DIR] [--no-stability]`` or ``reports.build.build_report``.

Modules, one job each: ``runs`` (a value with its reason; the seeds' pooling rule), ``aggregate``
(every number of the tables, computed from the results table ``smgs.cells.table``: seed and scene
means, paired differences, ranks), ``stats`` (scipy's t), ``paper`` (the paper's tables and names),
``table_model`` (ranking, footnotes, markdown, CSV), ``tables`` (Tables 1–5), ``tradeoff`` + ``plots``
(error against run time), ``diagnostics`` (k_max coverage, learned α/β/γ), ``stability`` (stiff-case
battery), ``environment`` (versions and machines), ``build``.
"""
