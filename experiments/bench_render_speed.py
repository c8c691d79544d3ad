"""Rendering speed of trained NeRFs against its error, setting by setting: rays/s and held-out
PSNR of every sample one chunk at a time (the renderer before front-to-back rendering), and of
each of `nerf.front_to_back`'s shortcuts alone and together (`render.DEFAULT`), with
`render.CHUNKS_IN_FLIGHT` chunks at once.

  python experiments/bench_render_speed.py --run stitch=RUN_DIR --run lego=RUN_DIR
      [--views N] [--chunk_size 4096] [--name bench_render_speed] [--results DIR]

For each run (a `signerf train` directory): its held-out views (the first N; all by default)
rendered with every setting of SETTINGS, side by side: the rays are cut into parts of a few
chunks and every setting renders each part in turn, in a rotating order, so that a machine
shared with other work slows every setting alike (the ratios are the medians of the parts'
ratios, and the rays/s the totals). A setting's first part is rendered once before timing
(compilation; its seconds are reported apart). Per setting: rays/s, its ratio to the first
setting's, the views' mean PSNR and its difference to the first setting's, and the largest
difference of a pixel's colour. Prints a table per run and writes <name>.json into --results
DIR (default outputs/experiments/), with the machine, its load and the code's commit, and
<name>.png: per run, its first held-out view's photo, rendered with every sample and with the
default settings, and their difference enlarged ten times.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

from signerf_jax import files
from signerf_jax.editing import figures
from signerf_jax.metrics import image as image_metrics
from signerf_jax.nerf import evaluate, render
from signerf_jax.nerf.commands import load_recorded_dataset
from signerf_jax.nerf.front_to_back import RenderSettings

import machine  # experiments/machine.py (this script's directory is on sys.path)
import results_dir

# Each shortcut alone (the others off), then together, as (settings, chunks in flight).
# "every sample, one chunk at a time" is the renderer as it was: every field and proposal
# sample evaluated whole, one chunk after another.
NONE_OF_THEM = RenderSettings(termination=0.0, colour_weight=0.0, field_sample_fraction=1.0,
                              empty_below=0.0)
IN_FLIGHT = render.CHUNKS_IN_FLIGHT
SETTINGS: dict[str, tuple[RenderSettings | None, int]] = {
    "every sample, one chunk at a time": (None, 1),
    "every sample": (None, IN_FLIGHT),
    "front to back, no shortcut": (NONE_OF_THEM, IN_FLIGHT),
    "termination 1e-2": (dataclasses.replace(NONE_OF_THEM, termination=1e-2), IN_FLIGHT),
    "colour where seen (1e-2)": (dataclasses.replace(NONE_OF_THEM, colour_weight=1e-2),
                                 IN_FLIGHT),
    "proposal grid (3e-3)": (dataclasses.replace(NONE_OF_THEM, empty_below=3e-3), IN_FLIGHT),
    "2/3 of the field samples": (dataclasses.replace(NONE_OF_THEM, field_sample_fraction=2 / 3),
                                 IN_FLIGHT),
    "default": (render.DEFAULT, IN_FLIGHT),
    "default, one chunk at a time": (render.DEFAULT, 1),
    "default before: termination 1e-3, grid 1e-3, pass 8": (
        dataclasses.replace(render.DEFAULT, termination=1e-3, empty_below=1e-3, first_pass=8),
        IN_FLIGHT),
    "default, every field sample": (dataclasses.replace(render.DEFAULT,
                                                        field_sample_fraction=1.0), IN_FLIGHT),
}
# Chunks a part holds: short enough that the load changes little within one part's turn.
CHUNKS_PER_PART = 4


def held_out_rays(held_out, views: int):
  """The first `views` held-out views' rays, flat [R]."""
  parts = [jax.tree.map(lambda a: np.asarray(a).reshape((-1,) + np.asarray(a).shape[2:]),
                        render.image_rays(held_out.cameras, index)) for index in range(views)]
  return jax.tree.map(lambda *arrays: np.concatenate(arrays), *parts)


def render_part(run, rays, chunk_size: int, setting) -> tuple[np.ndarray, float]:
  """The colours [R, 3] of rays [R] rendered with `setting` (settings, chunks in flight), and
  the seconds it took."""
  settings, render.CHUNKS_IN_FLIGHT = setting
  started = time.perf_counter()
  outputs = render.assemble(render.render_chunks(run.model, run.variables, rays, chunk_size,
                                                 settings=settings), rays.shape)
  return outputs["rgb"], time.perf_counter() - started


def measure_run(run_dir: Path, views: int | None, chunk_size: int
                ) -> tuple[dict[str, Any], list[np.ndarray]]:
  """Every setting's rays/s, ratio, PSNR and largest colour difference on the run's views,
  and the figure's row for the run ([H, W, 3] images)."""
  run = evaluate.load_run(run_dir)
  held_out = load_recorded_dataset(run.description, "eval")
  views = held_out.num_images if views is None else min(views, held_out.num_images)
  rays = held_out_rays(held_out, views)
  part = chunk_size * CHUNKS_PER_PART
  names = list(SETTINGS)
  first_seconds = {name: render_part(run, jax.tree.map(lambda a: a[:part], rays), chunk_size,
                                     SETTINGS[name])[1] for name in names}
  seconds: dict[str, list[float]] = {name: [] for name in names}
  images: dict[str, list[np.ndarray]] = {name: [] for name in names}
  for index, start in enumerate(range(0, rays.shape[0], part)):
    piece = jax.tree.map(lambda a, start=start: a[start:start + part], rays)
    for name in names[index % len(names):] + names[:index % len(names)]:
      rgb, spent = render_part(run, piece, chunk_size, SETTINGS[name])
      seconds[name].append(spent)
      images[name].append(rgb)
  shape = (views, held_out.height, held_out.width, 3)
  renders = {name: np.concatenate(images[name]).reshape(shape) for name in names}
  points = {}
  for name in names:
    psnr = float(np.mean([float(image_metrics.psnr_jit(renders[name][view],
                                                       held_out.images[view]))
                          for view in range(views)]))
    points[name] = {
        "settings": (None if SETTINGS[name][0] is None
                     else dataclasses.asdict(SETTINGS[name][0])),
        "chunks_in_flight": SETTINGS[name][1],
        "rays_per_second": rays.shape[0] / sum(seconds[name]),
        "ratio": float(np.median(np.asarray(seconds[names[0]]) / np.asarray(seconds[name]))),
        "held_out_psnr": psnr,
        "max_colour_difference": float(np.max(np.abs(renders[name] - renders[names[0]]))),
        "first_part_seconds": first_seconds[name]}
  base = points[names[0]]["held_out_psnr"]
  for point in points.values():
    point["psnr_difference_db"] = point["held_out_psnr"] - base
  entry = {"run": str(run_dir), "step_trained": run.step, "views": views,
           "image_size": [held_out.width, held_out.height], "chunk_size": chunk_size,
           "sampler": run.model.capacity.sampler, "settings": points}
  full, fast = renders[names[0]][0], renders["default"][0]
  return entry, [held_out.images[0], full, fast, np.clip(10 * np.abs(fast - full), 0, 1)]


def table(name: str, entry: dict[str, Any]) -> str:
  lines = [f"{name} ({entry['views']} held-out views, {entry['image_size'][0]} px, "
           f"{entry['sampler']} sampler)",
           f"  {'setting':44s} {'rays/s':>9s} {'ratio':>6s} {'PSNR':>7s} {'dPSNR':>7s} "
           f"{'max|d rgb|':>10s} {'1st part s':>10s}"]
  for setting, point in entry["settings"].items():
    lines.append(f"  {setting:44s} {point['rays_per_second']:9.0f} {point['ratio']:6.2f} "
                 f"{point['held_out_psnr']:7.3f} {point['psnr_difference_db']:+7.3f} "
                 f"{point['max_colour_difference']:10.1e} {point['first_part_seconds']:10.1f}")
  return "\n".join(lines)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
  parser.add_argument("--run", action="append", required=True, help="NAME=RUN_DIR")
  parser.add_argument("--views", type=int, default=None, help="held-out views (default: all)")
  parser.add_argument("--chunk_size", type=int, default=render.DEFAULT_CHUNK_SIZE)
  parser.add_argument("--name", default="bench_render_speed")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  result: dict[str, Any] = {"what": __doc__.split("\n\n")[0], "entries": {}}
  rows, labels = [], []
  for spec in args.run:
    name, run_dir = spec.split("=", 1)
    recorded = machine.record()
    entry, row = measure_run(Path(run_dir), args.views, args.chunk_size)
    rows.append(row)
    default = entry["settings"]["default"]
    labels.append([f"{name}: photo", "every sample",
                   f"default: {default['ratio']:.2f}x, {default['psnr_difference_db']:+.2f} dB",
                   "difference x10"])
    result["entries"][name] = {**entry, "machine": recorded,
                               "load_average_at_end": os.getloadavg(),
                               "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    print(table(name, entry), flush=True)
  args.results.mkdir(parents=True, exist_ok=True)
  files.write_json(args.results / f"{args.name}.json", result)
  files.write_image(args.results / f"{args.name}.png", figures.image_grid(rows, labels))


if __name__ == "__main__":
  main()
