"""Rendering speed against its error: held-out rays/s and PSNR of trained NeRFs, each rendered
with every sample and with fewer field samples (`Capacity.render_sample_fraction`).

  python experiments/bench_render_quality.py --run NAME=RUN_DIR [--fractions 1 0.667 0.5 0.333]
      [--name bench_render_quality]

For each run (a `signerf train` directory) and each fraction: every held-out view rendered by
`nerf.render.render_cameras` (chunks of 4096 rays) after one untimed view (compilation); rays/s
and the views' mean PSNR. Entries are added to <name>.json in --results DIR (default
outputs/experiments/) under NAME (an existing NAME is replaced), with the machine, its load and
the code's commit, and the json's entries are drawn as PSNR against rays/s (<name>.png).

It uses only APIs that older checkouts of this project have, so that the renderer as it was can
be measured on the same machine in the same hour: run it with `PYTHONPATH=<an older checkout>`
(a `git worktree`); a checkout without `render_sample_fraction` renders with every sample and
records fraction 1.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import signerf_jax
from signerf_jax import files
from signerf_jax.metrics import image as image_metrics
from signerf_jax.nerf import evaluate, render
from signerf_jax.nerf.commands import load_recorded_dataset

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine  # pylint: disable=wrong-import-position
import plotting  # pylint: disable=wrong-import-position
import results_dir  # pylint: disable=wrong-import-position

CHUNK_SIZE = 4096


def code_commit() -> str:
  """The commit of the checkout `signerf_jax` is imported from (an older one under PYTHONPATH)."""
  package = Path(signerf_jax.__file__).resolve().parent
  return subprocess.run(["git", "-C", str(package), "rev-parse", "HEAD"], capture_output=True,
                        text=True, check=True).stdout.strip()


def with_fraction(run, fraction: float):
  """The run rendering `fraction` of its field samples (older code: every sample, fraction 1)."""
  if not any(field.name == "render_sample_fraction"
             for field in dataclasses.fields(run.model.capacity)):
    return run, 1.0
  capacity = dataclasses.replace(run.model.capacity, render_sample_fraction=fraction)
  return dataclasses.replace(run, model=dataclasses.replace(run.model, capacity=capacity)), fraction


def measure(run, held_out) -> dict[str, Any]:
  """Rays/s and mean PSNR over every held-out view, rendering every sample of the fraction
  (where the code renders front to back by default, `settings=None` asks for every sample:
  experiments/bench_render_speed.py measures the front-to-back settings)."""
  every_sample = ({"settings": None} if "settings" in inspect.signature(
      render.render_cameras).parameters else {})
  render.render_cameras(run.model, run.variables, held_out.cameras.take([0]), CHUNK_SIZE,
                        **every_sample)
  started = time.perf_counter()
  renders = render.render_cameras(run.model, run.variables, held_out.cameras, CHUNK_SIZE,
                                  **every_sample)
  seconds = time.perf_counter() - started
  rays = held_out.num_images * held_out.width * held_out.height
  psnrs = [float(image_metrics.psnr_jit(renders["rgb"][index], held_out.images[index]))
           for index in range(held_out.num_images)]
  return {"seconds": seconds, "rays_per_second": rays / seconds,
          "held_out_psnr": float(np.mean(psnrs))}


def measure_run(run_dir: Path, fractions: list[float]) -> dict[str, Any]:
  run = evaluate.load_run(run_dir)
  held_out = load_recorded_dataset(run.description, "eval")
  points = {}
  for fraction in fractions:
    rendering, used = with_fraction(run, fraction)
    if f"{used:g}" not in points:
      points[f"{used:g}"] = measure(rendering, held_out)
  return {"run": str(run_dir), "step_trained": run.step, "code_commit": code_commit(),
          "views": held_out.num_images, "image_size": [held_out.width, held_out.height],
          "capacity": dataclasses.asdict(run.model.capacity), "by_render_sample_fraction": points}


def chart(entries: dict[str, Any], path: Path) -> None:
  series = []
  for name, entry in entries.items():
    points = sorted(entry["by_render_sample_fraction"].values(),
                    key=lambda point: point["rays_per_second"])
    series.append(plotting.Series(name, [point["rays_per_second"] / 1000 for point in points],
                                  [point["held_out_psnr"] for point in points]))
  plotting.write_panels(path, [plotting.line_chart(
      "held-out PSNR against rendering speed", series, "thousand rays / s", "PSNR (dB)",
      y_from_zero=False, width=560)])


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--run", action="append", required=True, help="NAME=RUN_DIR")
  parser.add_argument("--fractions", type=float, nargs="+", default=[1.0])
  parser.add_argument("--name", default="bench_render_quality")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  path = args.results / f"{args.name}.json"
  result = json.loads(path.read_text()) if path.exists() else {
      "what": __doc__.split("\n\n")[0], "entries": {}}
  for spec in args.run:
    name, run_dir = spec.split("=", 1)
    recorded = machine.record()
    entry = measure_run(Path(run_dir), args.fractions)
    result["entries"][name] = {**entry, "machine": recorded,
                               "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    print(name, json.dumps(entry["by_render_sample_fraction"]), flush=True)
  files.write_json(path, result)
  chart(result["entries"], path.with_suffix(".png"))


if __name__ == "__main__":
  main()
