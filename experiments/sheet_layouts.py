"""What the reference sheet's grid does to the objects the model paints: an edit's reference views
inpainted as sheets of several layouts and each alone.

    python experiments/sheet_layouts.py --edit DIR [--layouts 2x3 2x2 1x2] [--seeds 0 1 ... 7]
        [--results DIR] [--output JSON] [--gin_param ...]

DIR is an edit whose reference stage has run (`DIR/reference/inputs.npz`; `DIR/config.gin` gives
the model, the prompt and the first iteration's generation options). A layout of R x C tiles
holds R * C - 1 of the edit's reference views and the empty slot; with fewer tiles than views,
consecutive sheets take the views in turn, so that every view is painted. Singles inpaint each
view alone (the independent edits' way). For each way, over seeds and views, inside the
inpainting mask: `changed`, the share of pixels the generation changed by more than 0.1 in some
channel from the reference render; `difference`, the mean largest-channel change; `chroma`, the
mean max - min channel of the changed pixels (0: grey); `colour_spread`, the mean L1 distance
between the mean colours of the changed pixels of two views painted together (two tiles of one
sheet; for singles, two views with one seed; none for 1 x 2): how far the views disagree.
Writes the json and, beside it, a png: the reference renders, then each view as each way
painted it with the first seed.
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
from pathlib import Path

import jax
import numpy as np

from signerf_jax import configs, files
from signerf_jax.editing import commands, figures, generation
from signerf_jax.editing import sheet as sheet_lib

sys.path.insert(0, str(Path(__file__).resolve().parent))
import machine  # pylint: disable=wrong-import-position
import results_dir  # pylint: disable=wrong-import-position

CHANGE_THRESHOLD = 0.1  # The largest channel difference still counted as unchanged.


def view_measures(painted: np.ndarray, render: np.ndarray, mask: np.ndarray
                  ) -> tuple[float, float, float, np.ndarray]:
  """(changed share, mean difference, chroma, mean colour [3] of the changed pixels) of one
  painted view [h, w, 3] against its render, inside mask [h, w] (>= 0.5); chroma and colour are
  NaN where nothing changed."""
  inside = mask >= 0.5
  if not inside.any():
    raise ValueError("a reference view with an empty mask has nothing painted to measure")
  difference = np.abs(painted - render).max(-1)
  changed = inside & (difference > CHANGE_THRESHOLD)
  share, mean_difference = float(changed[inside].mean()), float(difference[inside].mean())
  if not changed.any():
    return share, mean_difference, np.nan, np.full(3, np.nan)
  pixels = painted[changed]
  return share, mean_difference, float((pixels.max(-1) - pixels.min(-1)).mean()), pixels.mean(0)


def summarize(groups: list[list[tuple]]) -> dict[str, float]:
  """The measures of views painted together (`groups` of `view_measures` results) averaged."""
  rows = [row for group in groups for row in group]
  spreads = [np.abs(a[3] - b[3]).sum() for group in groups
             for a, b in itertools.combinations(group, 2)]
  return {"changed": float(np.mean([row[0] for row in rows])),
          "difference": float(np.mean([row[1] for row in rows])),
          "chroma": float(np.nanmean([row[2] for row in rows])),
          "colour_spread": float(np.nanmean(spreads)) if spreads else None, "views": len(rows)}


def paint_sheets(generator: generation.Generator, tiles: dict[str, np.ndarray], rows: int,
                 columns: int, seeds: list[int]) -> tuple[list[list[tuple]], np.ndarray]:
  """Sheets of rows x columns over the reference views: (per sheet, its views' measures; each
  view as the first seed's first sheet holding it painted it [M, h, w, 3])."""
  count = len(tiles["render"])
  layout = sheet_lib.SheetLayout(rows, columns, tile_height=tiles["render"].shape[1],
                                 tile_width=tiles["render"].shape[2])
  per_sheet = layout.num_tiles
  sheet_views = [[(start + offset) % count for offset in range(per_sheet)]
                 for start in range(0, count, per_sheet)]
  groups, first, shown = [], np.zeros_like(tiles["render"]), set()
  recipes = [generation.SheetRecipe(seed) for seed in seeds]
  for views in sheet_views:
    inputs = generation.SheetInputs.from_tiles(tiles["render"][views], tiles["control"][views],
                                               tiles["mask"][views], layout)
    sheets = generation.generate_sheets(generator, inputs, recipes)
    painted = {recipe: np.asarray(sheet_lib.disassemble(sheets[recipe], layout)[0])
               for recipe in recipes}
    for tile, view in enumerate(views):
      if view not in shown:
        first[view] = painted[recipes[0]][tile]
        shown.add(view)
    groups += [[view_measures(painted[recipe][tile], tiles["render"][view], tiles["mask"][view])
                for tile, view in enumerate(views)] for recipe in recipes]
  return groups, first


def paint_singles(generator: generation.Generator, tiles: dict[str, np.ndarray],
                  seeds: list[int]) -> tuple[list[list[tuple]], np.ndarray]:
  """Every reference view alone, each seed's views with keys `generation.view_key(seed, view)`:
  (per seed, its views' measures; the first seed's views [M, h, w, 3]). All seeds' views go
  through the generator as one stream, so only the last batch is padded."""
  count = len(tiles["render"])
  views = np.tile(np.arange(count), len(seeds))
  keys = np.stack([generation.view_key(seed, view) for seed in seeds for view in range(count)])
  size = generator.batch_size
  painted = np.concatenate([
      generator(tiles["render"][views[start:start + size]],
                tiles["mask"][views[start:start + size], ..., None],
                tiles["control"][views[start:start + size], ..., None], keys[start:start + size])
      for start in range(0, len(views), size)])
  painted = painted.reshape((len(seeds),) + tiles["render"].shape)
  groups = [[view_measures(one_seed[view], tiles["render"][view], tiles["mask"][view])
             for view in range(count)] for one_seed in painted]
  return groups, painted[0]


def parse_layout(text: str) -> tuple[int, int]:
  rows, _, columns = text.partition("x")
  if not (rows.isdigit() and columns.isdigit()) or int(rows) * int(columns) < 2:
    raise argparse.ArgumentTypeError(
        f"a layout is ROWSxCOLUMNS with at least 2 cells, got {text!r}")
  return int(rows), int(columns)


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--edit", required=True, help="an edit whose reference stage has run")
  parser.add_argument("--layouts", nargs="+", type=parse_layout, default=[(2, 3), (2, 2), (1, 2)])
  parser.add_argument("--seeds", nargs="+", type=int, default=list(range(8)))
  results_dir.add_argument(parser)
  parser.add_argument("--output", metavar="JSON",
                      help="the json to write (default: DIR/sheet_layouts.json)")
  configs.add_gin_arguments(parser)
  args = parser.parse_args(argv)
  edit = Path(args.edit)
  inputs_path = edit / "reference" / "inputs.npz"
  if not inputs_path.is_file():
    raise SystemExit(f"{inputs_path}: no reference views here (run the edit's reference stage)")
  commands.parse_edit_config(edit, args.gin_file or [], args.gin_param)
  settings = commands.edit_settings()
  record = machine.record()
  tiles = {name: np.asarray(array, np.float32) for name, array in
           np.load(inputs_path).items() if name in ("render", "control", "mask")}
  config = settings.edit
  generator = generation.load_generator(config.model, config.controlnet, config.scheduler_kind,
                                        config.prompt, config.negative_prompt,
                                        settings.generation[0], settings.update.views_per_device,
                                        settings.attention, precision=config.diffusion_precision)
  ways = {}
  figure_rows, labels = [list(tiles["render"])], [["reference render"] * len(tiles["render"])]
  for rows, columns in args.layouts:
    groups, first = paint_sheets(generator, tiles, rows, columns, args.seeds)
    ways[f"sheet {rows}x{columns}"] = summarize(groups)
    figure_rows.append(list(first))
    labels.append([f"sheet {rows}x{columns}, seed {args.seeds[0]}"] * len(first))
  groups, first = paint_singles(generator, tiles, args.seeds)
  ways["single"] = summarize(groups)
  figure_rows.append(list(first))
  labels.append([f"alone, seed {args.seeds[0]}"] * len(first))
  for way, measures in ways.items():
    print(f"{way}: " + ", ".join(f"{name} {value:.3f}" for name, value in measures.items()
                                 if isinstance(value, float)), flush=True)
  output = Path(args.output or args.results / "sheet_layouts.json")
  files.write_json(output, {
      "what": "an edit's reference views inpainted as sheets of several layouts and alone "
              "(experiments/sheet_layouts.py's docstring says what each measure is)",
      "edit": str(edit.resolve()), "prompt": config.prompt, "seeds": args.seeds,
      "reference_views": len(tiles["render"]), "ways": ways, "devices": jax.device_count(),
      "machine": {**record, "load_average_at_end": os.getloadavg()}})
  files.write_image(output.with_suffix(".png"), figures.image_grid(figure_rows, labels))
  return 0


if __name__ == "__main__":
  sys.exit(main())
