"""``python -m blockray``: the command line (blockray/cli.py)."""

import sys

from .cli import main

sys.exit(main())
