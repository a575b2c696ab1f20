"""`python -m stim300`: the same command line as the `stim300` program."""

import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
