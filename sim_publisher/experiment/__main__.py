"""``python -m sim_publisher.experiment``: the experiment's command line (see :func:`cli`)."""

import sys

from sim_publisher.experiment import cli

if __name__ == "__main__":
    sys.exit(cli())
