"""The image set update's cost per view against its floor, one sheet-sized sampling: each view is
inpainted in the empty slot of its own copy of the sheet, so a view cannot cost less than the
sampler's UNet + ControlNet on one sheet; batching views (`UpdateConfig.views_per_device`)
should bring the cost per view down to that or below.

  python experiments/bench_update.py [--views 8] [--batches 1 4 8] [--steps 20] [--repeats 3]

With the shipped model at its native tile size and the default 2 x 3 sheet, on random views of
--view_size pixels (the cost does not depend on the pixels), it measures in one run:
  * the floor: one sheet generated alone (`generation.generate_sheets`, one view per device), as
    the reference sheet is, timed in turn with the update (the machine's load changes both);
  * per views-per-batch setting: wall and CPU (this process's) seconds per view updating the
    views batch after batch, and their ratios to the floor's; the first batch's seconds (it
    compiles) and those of a batch of one view (the last batch of an update: it runs the
    programs the full batches compiled, padded);
  * the breakdown of one batch, per view: cutting the tiles and assembling the sheets, the
    control embedding of the cells the slot reaches (and, for comparison, of whole sheets, what
    the sampler computes when not given it), the sampler (of which the VAE encode and decode,
    timed apart; the rest is the denoising loop: UNet + ControlNet on both guidance halves at
    every step), cutting the slots out and pasting them back, the copy to the host, the PNG
    writes; and what the update computes once (the sheet on the devices and its embedding);
  * `update.run_update` end to end (loading, padding of the last batch, PNG writes into a
    scratch folder), per view.
Views whose mask is empty never reach the update (the stage passes only the views that show the
selection: `EditContext.visible_views`), so they cost nothing. Writes NAME.json (default
bench_update) with the machine and load into --results DIR (default outputs/experiments/).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import time
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax import files
from signerf_jax.diffusion import layers
from signerf_jax.diffusion import vae as vae_lib
from signerf_jax.diffusion.pipeline import GenerationOptions
from signerf_jax.editing import crops, generation, update
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing.config import DEFAULT_MODEL_DIR

import machine  # experiments/machine.py (this script's directory is on sys.path)
import results_dir  # experiments/results_dir.py (this script's directory is on sys.path)


def random_views(count: int, size: int, rng: np.random.Generator) -> update.SlotViews:
  """`count` square views of `size` pixels with a centred square mask (whole frames as tiles)."""
  masks = np.zeros((count, size, size), np.float32)
  masks[:, size // 4:3 * size // 4, size // 4:3 * size // 4] = 1.0
  return update.SlotViews(
      images=rng.random((count, size, size, 3), np.float32), masks=masks,
      controls=rng.random((count, size, size), np.float32),
      boxes=np.asarray(crops.full_frame_boxes(count, size, size, size, size)))


def take(views: update.SlotViews, start: int, count: int) -> update.SlotViews:
  return update.SlotViews(*(getattr(views, field.name)[start:start + count]
                            for field in dataclasses.fields(views)))


def timed(function: Callable[[], object]) -> tuple[float, float]:
  """(wall, CPU) seconds of `function()` and everything it dispatched."""
  wall, cpu = time.perf_counter(), time.process_time()
  jax.block_until_ready(function())
  return time.perf_counter() - wall, time.process_time() - cpu


def keys_of(count: int) -> np.ndarray:
  return np.stack([generation.view_key(0, index) for index in range(count)])


def one_sheet(generator: generation.Generator, layout: sheet_lib.SheetLayout,
              rng: np.random.Generator) -> Callable[[], object]:
  """The floor: generates one reference sheet (every tile masked, the slot empty) with one
  view per device, as `generation.generate_sheets` makes the reference sheet."""
  tiles = layout.num_tiles, layout.tile_height, layout.tile_width
  inputs = generation.SheetInputs.from_tiles(rng.random((*tiles, 3), np.float32),
                                             rng.random(tiles, np.float32),
                                             np.ones(tiles, np.float32), layout)
  alone = dataclasses.replace(generator, views_per_device=1)
  recipe = generation.SheetRecipe(0)
  return lambda: generation.generate_sheets(alone, inputs, [recipe])[recipe]


def update_all(edit_batch: update.EditBatch, views: update.SlotViews, batch_size: int
               ) -> Callable[[], object]:
  """Updates every view, batch after batch (each one finished before the next)."""
  keys = keys_of(len(views.images))
  return lambda: [jax.block_until_ready(edit_batch(take(views, start, batch_size),
                                                   keys[start:start + batch_size]))
                  for start in range(0, len(keys), batch_size)]


def seconds_per_view(edit_batch: update.EditBatch, views: update.SlotViews, batch_size: int
                     ) -> float:
  """Wall seconds per view to update every view in batches of `batch_size` (after a warm-up
  batch that compiles)."""
  jax.block_until_ready(edit_batch(take(views, 0, batch_size), keys_of(batch_size)))
  return timed(update_all(edit_batch, views, batch_size))[0] / len(views.images)


def versus_floor(floor: Callable[[], object], updates: Callable[[], object], count: int,
                 repeats: int) -> dict:
  """The floor and the update of `count` views timed in turn `repeats` times: medians per
  view and their ratios (wall and CPU)."""
  floor_times, update_times = [], []
  for _ in range(repeats):
    floor_times.append(timed(floor))
    update_times.append(np.asarray(timed(updates)) / count)
  floor_median, update_median = np.median(floor_times, axis=0), np.median(update_times, axis=0)
  return {"floor_seconds": round(float(floor_median[0]), 4),
          "floor_cpu_seconds": round(float(floor_median[1]), 4),
          "seconds_per_view": round(float(update_median[0]), 4),
          "cpu_seconds_per_view": round(float(update_median[1]), 4),
          "per_view_over_floor": round(float(update_median[0] / floor_median[0]), 3),
          "cpu_per_view_over_floor": round(float(update_median[1] / floor_median[1]), 3),
          "per_view_over_floor_each_repeat": [round(float(u[0] / f[0]), 3)
                                              for u, f in zip(update_times, floor_times)]}


def vae_programs(generator: generation.Generator):
  """Jitted VAE encode ([B, H, W, 3] in [-1, 1], noise) and decode (latents) of the sampler's
  networks, with its convolution choices."""
  models = generator.pipeline.models

  def in_context(function):
    def run(*arguments):
      with layers.winograd_convolutions(generator.winograd_convolutions):
        return function(*arguments)
    return jax.jit(run)

  encode = in_context(lambda images, noise: vae_lib.encode_to_latents(
      models.vae, models.vae_params, images, noise))
  decode = in_context(lambda latents: vae_lib.decode_from_latents(
      models.vae, models.vae_params, latents))
  return encode, decode


def batch_parts(generator: generation.Generator, sheet: update.SlotSheet,
                layout: sheet_lib.SheetLayout, views: update.SlotViews, keys: np.ndarray,
                scratch: Path) -> dict[str, Callable[[], object]]:
  """`update.update_batch`'s parts (and the VAE's share of the sampler), each a function of the
  outputs the parts before it left in `state`."""
  state: dict = {}
  encode, decode = vae_programs(generator)
  latent_shape = (generator.batch_size,
                  *(size // generator.latent_factor for size in layout.sheet_shape), 4)
  noise = jnp.asarray(np.random.default_rng(0).standard_normal(latent_shape), jnp.float32)

  def tiles():
    state["padded"], view_tiles = update.padded_tiles(generator, views, layout)
    state["inputs"] = sheet_lib.slot_update_inputs(sheet.rgb, sheet.control, *view_tiles,
                                                   layout=layout)
    return state["inputs"]

  def embedding():
    state["embedding"] = generator.control_embedding(state["inputs"][1], sheet.control_embedding,
                                                     layout.slot_region)
    return state["embedding"]

  def sampler():
    image, control, mask = state["inputs"]
    state["generated"] = generator.dispatch(image, mask, control, keys, state["embedding"])
    return state["generated"]

  def paste():
    padded = state["padded"]
    state["slots"] = sheet_lib.slot_tiles(state["generated"], layout)
    state["edited"] = crops.paste_tiles(padded.images, state["slots"], padded.boxes,
                                        padded.masks)
    return state["edited"]

  def to_host():
    state["host"] = np.asarray(state["edited"]), np.asarray(state["slots"])
    return state["host"][0]

  def png_writes():
    for index, (image, slot) in enumerate(zip(*state["host"])):
      files.write_image(scratch / "tiles" / f"{index}.png", slot)
      files.write_image(scratch / "images" / f"{index}.png", image)

  return {"tiles_and_sheets": tiles, "control_embedding_of_the_slot": embedding,
          "sampler": sampler, "slots_and_paste_back": paste, "copy_to_host": to_host,
          "png_writes": png_writes,
          "control_embedding_of_whole_sheets": lambda: generator.control_embedding(
              state["inputs"][1]),
          "vae_encode": lambda: encode(2 * state["inputs"][0] - 1, noise),
          "vae_decode": lambda: decode(noise)}


def breakdown(generator: generation.Generator, sheet_arrays, layout: sheet_lib.SheetLayout,
              views: update.SlotViews, repeats: int) -> dict[str, float]:
  """Seconds per view of each part of one full batch (the least of `repeats`)."""
  batch = take(views, 0, generator.batch_size)
  seconds = {"once_per_update_sheet_and_embedding": timed(
      lambda: update.SlotSheet.prepare(generator, *sheet_arrays))[0]}
  sheet = update.SlotSheet.prepare(generator, *sheet_arrays)
  with tempfile.TemporaryDirectory() as scratch:
    parts = batch_parts(generator, sheet, layout, batch, keys_of(generator.batch_size),
                        Path(scratch))
    for function in parts.values():  # Compiles.
      jax.block_until_ready(function())
    for _ in range(repeats):
      for name, function in parts.items():
        seconds[name] = min(seconds.get(name, np.inf), timed(function)[0])
  seconds["denoising_loop_and_rest_of_sampler"] = (
      seconds["sampler"] - seconds["vae_encode"] - seconds["vae_decode"])
  return {name: round(value / generator.batch_size, 4) for name, value in seconds.items()}


def end_to_end(generator: generation.Generator, edit_batch: update.EditBatch,
               views: update.SlotViews, floor: Callable[[], object]) -> dict[str, float]:
  """`update.run_update` over the views into a scratch folder: wall and CPU seconds per view,
  and their ratios to the floor's timed just before and just after it."""
  count = len(views.images)
  with tempfile.TemporaryDirectory() as scratch:
    run = lambda: update.run_update(generator, edit_batch, np.arange(count),
                                    lambda indices: take(views, int(indices[0]), len(indices)),
                                    scratch, seed=0, progress=False)
    before = timed(floor)
    seconds = np.asarray(timed(run)) / count
    floor_mean = (np.asarray(before) + np.asarray(timed(floor))) / 2
  return {"seconds_per_view": round(float(seconds[0]), 4),
          "cpu_seconds_per_view": round(float(seconds[1]), 4),
          "per_view_over_floor": round(float(seconds[0] / floor_mean[0]), 3),
          "cpu_per_view_over_floor": round(float(seconds[1] / floor_mean[1]), 3)}


def measure(model: str, layout: sheet_lib.SheetLayout, options: GenerationOptions,
            views: update.SlotViews, sheet_arrays, batch_size: int, repeats: int) -> dict:
  """Everything the module docstring lists for one views-per-batch setting."""
  generator = generation.load_generator(model, "", "", "a red cow", "", options, batch_size)
  edit_batch = update.batch_editor(generator, layout, "sheet", *sheet_arrays)
  keys = keys_of(batch_size)
  first_batch = timed(lambda: edit_batch(take(views, 0, batch_size), keys))[0]
  floor = one_sheet(generator, layout, np.random.default_rng(1))
  jax.block_until_ready(floor())  # Compiles.
  result = {"views_per_batch": batch_size, "first_batch_seconds": round(first_batch, 2),
            **versus_floor(floor, update_all(edit_batch, views, batch_size),
                           len(views.images), repeats)}
  result["full_batch_seconds"] = round(timed(
      lambda: edit_batch(take(views, 0, batch_size), keys))[0], 3)
  result["one_view_batch_seconds"] = round(timed(
      lambda: edit_batch(take(views, 0, 1), keys[:1]))[0], 3)
  result["breakdown_seconds_per_view"] = breakdown(generator, sheet_arrays, layout, views,
                                                   repeats)
  result["end_to_end"] = end_to_end(generator, edit_batch, views, floor)
  return result


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--views", type=int, default=8, help="views updated per batch size")
  parser.add_argument("--batches", type=int, nargs="+", default=[1, 4, 8],
                      help="views per device (one device here)")
  parser.add_argument("--steps", type=int, default=20, help="sampler steps")
  parser.add_argument("--view_size", type=int, default=512, help="views' pixels (square)")
  parser.add_argument("--repeats", type=int, default=3,
                      help="times the floor and the update are timed in turn")
  parser.add_argument("--name", default="bench_update")
  results_dir.add_argument(parser)
  args = parser.parse_args()
  record = machine.record(jax_devices=str(jax.devices()))
  model = str(DEFAULT_MODEL_DIR)
  tile = generation.native_tile_size(model)
  layout = sheet_lib.SheetLayout(2, 3, -1, -1, tile, tile)
  rng = np.random.default_rng(0)
  views = random_views(args.views, args.view_size, rng)
  sheet_arrays = (rng.random((*layout.sheet_shape, 3), np.float32),
                  rng.random((*layout.sheet_shape, 1), np.float32))
  options = GenerationOptions(num_inference_steps=args.steps, guidance_scale=5.0)
  results = []
  for batch_size in args.batches:
    results.append(measure(model, layout, options, views, sheet_arrays, batch_size,
                           args.repeats))
    print(results[-1], flush=True)
  args.results.mkdir(parents=True, exist_ok=True)
  files.write_json(args.results / f"{args.name}.json", {
      "machine": {**record, "load_average_after": os.getloadavg()},
      "model": "shipped", "tile_size": tile, "sheet": "2 x 3",
      "sheet_pixels": list(layout.sheet_shape), "view_pixels": [args.view_size] * 2,
      "options": dataclasses.asdict(options), "views": args.views, "repeats": args.repeats,
      "results": results})


if __name__ == "__main__":
  main()
