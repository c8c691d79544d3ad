"""The image set update's cost per view against one sheet: each view is inpainted in the empty
slot of its own copy of the sheet, so a view costs one sheet-sized UNet + ControlNet sampling;
batching views (`UpdateConfig.views_per_device`) should bring the cost per view down to that or
below, and the one-view-at-a-time loop (batch 1) is the reference.

  python experiments/bench_update.py [--views 8] [--batches 1 4 8] [--steps 20]

With the shipped model at its native tile size and the default 2 x 3 sheet, on random views
(the cost does not depend on the pixels). Views whose mask is empty never reach the update (the
stage passes only the views that show the selection: `EditContext.visible_views`), so they cost
nothing. Writes NAME.json (default bench_update) with the machine and load into --results DIR
(default outputs/experiments/).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time

import jax
import numpy as np

from signerf_jax import files
from signerf_jax.diffusion.pipeline import GenerationOptions
from signerf_jax.editing import crops, generation, update
from signerf_jax.editing.config import DEFAULT_MODEL_DIR
from signerf_jax.editing.sheet import SheetLayout

import machine  # experiments/machine.py (this script's directory is on sys.path)
import results_dir  # experiments/results_dir.py (this script's directory is on sys.path)


def random_views(count: int, size: int, rng: np.random.Generator) -> update.SlotViews:
  """`count` square views of `size` pixels with a centred square mask."""
  masks = np.zeros((count, size, size), np.float32)
  masks[:, size // 4:3 * size // 4, size // 4:3 * size // 4] = 1.0
  return update.SlotViews(
      images=rng.random((count, size, size, 3), np.float32), masks=masks,
      controls=rng.random((count, size, size), np.float32),
      boxes=np.asarray(crops.full_frame_boxes(count, size, size, size, size)))


def seconds_per_view(edit_batch, views: update.SlotViews, batch_size: int) -> float:
  """Wall seconds per view to update every view in batches of `batch_size` (after a warm-up
  batch that compiles)."""
  keys = np.stack([generation.view_key(0, index) for index in range(len(views.images))])
  take = lambda start: update.SlotViews(*(getattr(views, field.name)[start:start + batch_size]
                                          for field in dataclasses.fields(views)))
  edit_batch(take(0), keys[:batch_size])  # Compiles.
  start = time.perf_counter()
  for first in range(0, len(keys), batch_size):
    edit_batch(take(first), keys[first:first + batch_size])
  return (time.perf_counter() - start) / len(keys)


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--views", type=int, default=8, help="views updated per batch size")
  parser.add_argument("--batches", type=int, nargs="+", default=[1, 4, 8],
                      help="views per device (one device here)")
  parser.add_argument("--steps", type=int, default=20, help="sampler steps")
  parser.add_argument("--name", default="bench_update")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  load_before = os.getloadavg()
  model = str(DEFAULT_MODEL_DIR)
  tile = generation.native_tile_size(model)
  layout = SheetLayout(2, 3, -1, -1, tile, tile)
  rng = np.random.default_rng(0)
  views = random_views(args.views, tile, rng)
  sheet_rgb = rng.random((2 * tile, 3 * tile, 3), np.float32)
  sheet_control = rng.random((2 * tile, 3 * tile, 1), np.float32)
  options = GenerationOptions(num_inference_steps=args.steps, guidance_scale=5.0)
  results = []
  for batch_size in args.batches:
    generator = generation.load_generator(model, "", "", "a red cow", "", options, batch_size)
    edit_batch = update.batch_editor(generator, layout, "sheet", sheet_rgb, sheet_control)
    seconds = seconds_per_view(edit_batch, views, batch_size)
    results.append({"views_per_batch": batch_size, "seconds_per_view": round(seconds, 4),
                    "views_per_second": round(1 / seconds, 3)})
    print(results[-1], flush=True)
  one_at_a_time = next((result["seconds_per_view"] for result in results
                        if result["views_per_batch"] == 1), None)
  for result in results:
    # A batch of 1 is exactly one sheet-sized sampling: the per-view cost against it.
    result["per_view_over_one_sheet"] = (None if one_at_a_time is None else
                                         round(result["seconds_per_view"] / one_at_a_time, 3))
  args.results.mkdir(parents=True, exist_ok=True)
  files.write_json(args.results / f"{args.name}.json", {
      "machine": {"platform": platform.platform(), "processor": platform.processor(),
                  "cpu_count": os.cpu_count(), "jax_devices": str(jax.devices()),
                  "load_average_before": load_before, "load_average_after": os.getloadavg(),
                  **machine.code_version()},
      "model": "shipped", "tile_size": tile, "sheet": "2 x 3",
      "sheet_pixels": [2 * tile, 3 * tile], "options": dataclasses.asdict(options),
      "views": args.views, "results": results})


if __name__ == "__main__":
  main()
