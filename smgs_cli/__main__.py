"""``python -m smgs_cli``: the ``smgs`` command where its script is not on PATH."""

import sys

from smgs_cli.main import main

sys.exit(main())
