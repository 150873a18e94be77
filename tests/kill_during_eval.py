"""A sweep of the ``counting`` method (tests/counting_method.py) started as the command line starts it,
that kills itself with a signal at a stage of the final evaluation: for tests/test_final_checkpoint.py.

    python tests/kill_during_eval.py STAGE SIGNAL HYDRA_ARGS...

STAGE names a function of ``protocols.train_loop`` (``final_metrics``: the metrics and LPIPS;
``measure_render_fps``; ``consistency``: the video frames); SIGNAL is TERM or KILL."""

from __future__ import annotations

import os
import signal
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(stage: str, sig: str, args: list[str]) -> None:
    import protocols.train_loop as loop
    from baselines.method import MethodSpec
    from baselines.registry import register
    from counting_method import Counting
    from protocols.run import cli

    register(MethodSpec("counting", Counting, {"mode": "3dgs"}))
    real = getattr(loop, stage)

    def killed(*a, **kw):
        os.kill(os.getpid(), getattr(signal, f"SIG{sig}"))
        return real(*a, **kw)

    setattr(loop, stage, killed)
    sys.argv = ["protocols.run", *args]
    cli()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3:])
