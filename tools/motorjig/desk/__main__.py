"""python -m motorjig.desk: start MotorJig Desk (what `make` runs with --bench when no board is attached)."""

import sys

from motorjig.desk.server import main

if __name__ == "__main__":
    sys.exit(main())
