"""The ``smgs`` command: one front door to the harness's programs (``smgs --help``).

The top layer of the imports (smgs <- baselines <- protocols <- reports <- smgs_cli): each
subcommand is a thin call into the module that does the work, which also runs on its own
(``smgs run ...`` is ``python -m protocols.run ...``).
"""
