"""Run results: one run's results.json (``result``), a tree of them read as one set of cells
(``tree``) and that set as pandas tables (``table``: ``smgs.results``, ``smgs.curves``)."""
