"""The detached kernel build: ``python -m torchcontact.kernels NAME SOURCE.cpp``.

Started by :func:`torchcontact.kernels.compiled` for a background build, in its own process
session, so the build finishes and fills the disk cache even when the process that asked for it
exits first (a short CLI run), and the compiler never holds the caller's GIL.
"""

import sys
from pathlib import Path

from torchcontact.kernels import build_source

if __name__ == "__main__":
    build_source(sys.argv[1], Path(sys.argv[2]))
