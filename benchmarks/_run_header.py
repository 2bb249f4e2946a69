"""The two comment lines every render benchmark prints first: the machine and the command."""

import os
import platform
import sys

import numpy as np


def print_run_header():
    print(f"# {platform.node()} {platform.processor() or platform.machine()} cores={os.cpu_count()} "
          f"python={platform.python_version()} numpy={np.__version__}", flush=True)
    print(f"# command: {' '.join([os.path.basename(sys.argv[0])] + sys.argv[1:])}", flush=True)
