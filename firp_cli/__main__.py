"""``python -m firp_cli``: the ``firp`` command without the console script installed."""

import sys

from firp_cli import main

if __name__ == "__main__":
    sys.exit(main())
