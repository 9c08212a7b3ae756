"""``python -m clients.view [OPTIONS]``: the same as ``shapeloc view [OPTIONS]`` (the options
and their defaults: ``shapeloc view --help``)."""

import sys

from clients.__main__ import cli

if __name__ == "__main__":
    sys.exit(cli(["view", *sys.argv[1:]]))
