"""Where the experiments write their results: the folder `--results DIR` names, by default
outputs/experiments/ under the working directory (git ignores /outputs/).

experiments/results/ holds the committed result of each experiment (its README.md indexes them):
a run never writes there by default, so committing a result is a deliberate copy, e.g.

    python experiments/bench_nerf.py
    cp outputs/experiments/bench_nerf.* outputs/experiments/bench_nerf_*.png experiments/results/
"""

from __future__ import annotations

import argparse
from pathlib import Path

DEFAULT = Path("outputs") / "experiments"


def add_argument(parser: argparse.ArgumentParser) -> None:
  """Adds `--results DIR` (a Path, default outputs/experiments) to `parser`."""
  parser.add_argument(
      "--results", type=Path, default=DEFAULT, metavar="DIR",
      help="the folder to write the results into (default: %(default)s, under the working "
      "directory; experiments/results/ holds the committed ones)")
