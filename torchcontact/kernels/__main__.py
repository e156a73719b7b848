"""Build one kernel source of the cache: ``python -m torchcontact.kernels NAME SOURCE.cpp``.

:func:`torchcontact.kernels.build_source` from the command line (locked, bounded, published
atomically). Background builds run ``torchcontact/kernels/_store.py`` by path instead, which
imports no torch.
"""

import sys
from pathlib import Path

from torchcontact.kernels import build_source

if __name__ == "__main__":
    build_source(sys.argv[1], Path(sys.argv[2]))
