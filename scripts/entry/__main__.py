"""``python -m rlpipe``: the ``rlpipe`` command (``rlpipe.scripts.cli``), for a Python whose scripts folder is not on PATH."""

import sys

from rlpipe.scripts.cli import main

if __name__ == "__main__":
    sys.exit(main())
