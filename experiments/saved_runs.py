"""A training run's files kept between sessions: its checkpoint, config and per-epoch log
(about 1 MB in all), copied from ``runs/`` to ``experiments/checkpoints/`` to be
committed, and back into a fresh machine's ``runs/`` to be resumed with ``--resume``.
Used by ``ablations.py`` and ``train_comparison.sh``:

    python experiments/saved_runs.py runs/kpn-diverse-x2 experiments/checkpoints/kpn-diverse-x2

exits 0 when ``SRC`` had a checkpoint and was copied, 1 when it had none (nothing copied).
"""

from __future__ import annotations

import sys

from common import copy_run

def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2 or argv[0] in ("-h", "--help"):
        print(__doc__)
        return 2
    src, dst = argv
    if not copy_run(src, dst):
        return 1
    print(f"copied {src} -> {dst}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
