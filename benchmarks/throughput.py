"""Throughput of every env against the published code's speed.

    .venv/bin/python benchmarks/throughput.py [beacon-torch bench options]

The same as ``beacon-torch bench``: a table while it runs, then ``results.csv``,
``results.json`` and ``throughput.png`` in ``--out`` (default a new runs/bench/bench-DATE-TIME). The numbers
recorded in benchmarks/RESULTS.md come from this script.
"""

import sys

from beacon_torch.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
