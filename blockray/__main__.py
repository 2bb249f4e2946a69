"""``python -m blockray``: the command line (host_driver/cli.py)."""

import sys

from .host_driver.cli import main

sys.exit(main())
