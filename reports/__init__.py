"""Reports: run results -> report.md, report.html, one CSV per table and PNG plots, the paper's numbers beside ours.

``python -m reports.build RUNS_DIR... [--out DIR] [--no-stability]`` or ``reports.build.build_report``.

Modules, one job each: ``runs`` (a value with its reason; the seeds' pooling rule), ``aggregate``
(every number of the tables, computed from the results table ``smgs.cells.table``: seed and scene
means, paired differences, ranks), ``stats`` (scipy's t), ``paper`` (the paper's tables and names),
``table_model`` (footnotes, markdown, CSV), ``tables`` (Tables 1–5), ``paired``, ``ordering`` and
``collapse`` (their sub-tables and footnotes), ``tradeoff`` + ``plots`` (error against run time),
``diagnostics`` (k_max coverage, learned α/β/γ), ``stability_section`` (stiff-case battery),
``popping`` (the flip scenes), ``environment`` (versions and machines), ``commands`` (the command
lines' parsers), ``build``; ``html/`` (report.html).
"""
