"""This checkout's packages for a benchmark and the processes it starts, not the installed ones.

The venv's editable install maps ``bridge``, ``twin``, ``controller`` and ``server`` to the
checkout it was installed from; a benchmark run from another checkout (a worktree, a fresh clone
measured with the first one's venv) would time that one's code and print it as its own. Import
this module before any of the project's: it puts the checkout's root first on ``sys.path`` (the
editable finder comes after the path finder) and on ``PYTHONPATH`` for the children (``xneck``,
``python -m bridge ...``), which read it before their site-packages.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

if sys.path[:1] != [str(ROOT)]:
    sys.path.insert(0, str(ROOT))
os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT), *(p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep)
                                                         if p and p != str(ROOT))])
