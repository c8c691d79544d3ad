"""Does the sheet separate from each baseline run after run? A tally over stored runs of
experiments/nerf_consistency.py.

    python experiments/nerf_consistency_runs.py --setting NAME RESULT.json [RESULT.json ...]
        [--setting ...] [--results DIR] [--output JSON]

Each RESULT.json is one run of nerf_consistency.py (e.g. one seed); the runs given after one
--setting are repeats of the same setting. For every run, scene, baseline and per-view measure
(fit PSNR, solidity IoU, mean opacity) the comparison is recomputed from the stored per-view
values (`nerf_consistency.compare_arms`): the sheet's interval against the baseline's
(unpaired: "higher", "lower", "overlapping") and the view-by-view difference sheet - baseline
(paired: its interval and whether it leaves out zero). Per setting, scene, baseline and
measure: how many runs put the sheet higher and lower under each comparison.

Writes the json and, beside it, a png: per setting and measure, each run's paired difference
interval (run N: the setting's Nth file; zero marked), the sheet above the baseline right of
zero.
"""

from __future__ import annotations

import argparse
import datetime
import sys
from pathlib import Path
from typing import Any

import numpy as np

from signerf_jax import files
from signerf_jax.errors import InputError

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine  # pylint: disable=wrong-import-position
import nerf_consistency  # pylint: disable=wrong-import-position
import plotting  # pylint: disable=wrong-import-position
import results_dir  # pylint: disable=wrong-import-position


def run_comparisons(result: dict[str, Any], source: Path) -> dict[str, Any]:
  """Per scene of one stored run: `nerf_consistency.compare_arms` of its arms."""
  try:
    return {scene: nerf_consistency.compare_arms(stored["arms"])
            for scene, stored in result["scenes"].items()}
  except KeyError as error:
    raise InputError(f"not a nerf_consistency.py result with per-view values (no {error})",
                     source) from error
  except InputError as error:  # Per-view values of two arms that cannot be paired.
    raise InputError(error.problem, source, error.field) from error


def tally(runs: dict[str, dict[str, Any]]) -> dict[str, Any]:
  """Per scene, baseline and per-view measure: runs with the sheet higher / lower, unpaired
  (intervals apart) and paired (the difference's interval leaves out zero)."""
  counts: dict[str, Any] = {}
  for comparisons in runs.values():
    for scene, compared in comparisons.items():
      for baseline, differences in compared["sheet_minus"].items():
        for key, difference in differences.items():
          count = counts.setdefault(scene, {}).setdefault(baseline, {}).setdefault(key, {
              "runs": 0, "unpaired": {"higher": 0, "lower": 0},
              "paired": {"higher": 0, "lower": 0}})
          count["runs"] += 1
          unpaired = compared["sheet_against"][baseline][key]
          if unpaired in ("higher", "lower"):
            count["unpaired"][unpaired] += 1
          if difference["significant"]:
            count["paired"]["higher" if difference["mean"] > 0 else "lower"] += 1
  return counts


def figure(settings: dict[str, dict[str, Any]]) -> np.ndarray:
  """[H, W, 3] float32 RGB: a row per setting, scene and baseline; a chart per per-view measure
  with each run's paired difference interval below a zero mark."""
  rows = []
  for name, setting in settings.items():
    runs = list(setting["runs"].values())
    for scene, compared in runs[0].items():
      for baseline in compared["sheet_minus"]:
        panels = []
        for key, title, unit in nerf_consistency.MEASURES:
          if key not in compared["sheet_minus"][baseline]:
            continue
          chart_rows = [("zero", 0.0, 0.0, 0.0)] + [
              (f"run {number}", difference["mean"], *(difference["interval"] or (None,) * 2))
              for number, comparisons in enumerate(runs, start=1)
              for difference in [comparisons[scene]["sheet_minus"][baseline][key]]]
          panels.append(plotting.interval_chart(
              f"{name}: sheet - {baseline}, {unit}", chart_rows, title, width=560,
              height=60 + 24 * len(chart_rows)))
        rows.append(plotting.side_by_side(panels))
  return plotting.stacked(rows)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--setting", nargs="+", action="append", required=True,
                      metavar="NAME RESULT.json", help="a setting's name and its runs")
  results_dir.add_argument(parser)
  parser.add_argument("--output", metavar="JSON",
                      help="the json to write (default: DIR/nerf_consistency_runs.json)")
  args = parser.parse_args(argv)
  settings = {}
  try:
    for name, *paths in args.setting:
      if not paths:
        raise InputError(f"setting {name!r} needs one or more result files after its name",
                         field="--setting")
      runs = {path: run_comparisons(files.read_json(Path(path)), Path(path)) for path in paths}
      settings[name] = {"runs": runs, "tally": tally(runs)}
  except InputError as error:
    print(f"nerf_consistency_runs: error: {error}", file=sys.stderr)
    return 2
  output = Path(args.output or args.results / "nerf_consistency_runs.json")
  files.write_json(output, {"what": "experiments/nerf_consistency_runs.py over stored runs",
                            "date": datetime.date.today().isoformat(),
                            **machine.code_version(),
                            "settings": settings})
  files.write_image(output.with_suffix(".png"), figure(settings))
  for name, setting in settings.items():
    print(f"nerf_consistency_runs: {name}: {setting['tally']}")
  print(f"nerf_consistency_runs: -> {output}, {output.with_suffix('.png')}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
