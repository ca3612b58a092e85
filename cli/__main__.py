"""`python -m cli ...` is `macb ...`: services and tests start the command this way, with
the interpreter they run under rather than whichever `macb` is on PATH."""

import sys

from cli.main import entry

if __name__ == "__main__":
    sys.exit(entry())
