"""`python -m calibd`: the same command line as the `calibd` program."""

import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
