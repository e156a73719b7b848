"""``python -m torchcontact``: the command line, exiting through the interpreter's shutdown.

The ``torchcontact`` console script (:func:`torchcontact.cli.console_main`) skips that shutdown;
this entry keeps it, as any in-process caller of :func:`torchcontact.cli.main` does.
"""

import sys

from torchcontact.cli import main

if __name__ == "__main__":
    sys.exit(main())
