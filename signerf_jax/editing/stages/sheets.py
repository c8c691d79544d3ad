"""The preview and sheet stages (paper, Sec. 3 step 5, "Reference Sheet").

The preview generates candidate sheets for several seeds (and re-rolls of some tiles) side by
side, so the user can pick one; the sheet stage makes the chosen recipe, reusing the preview's
candidate when it was made from the same reference tiles with the same settings.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable

import numpy as np
import tqdm

from signerf_jax import files
from signerf_jax.editing import figures, generation
from signerf_jax.editing.project import canonical_json, load_arrays, save_arrays
from signerf_jax.editing.stages.context import EditContext

# A lookup of candidate sheets already generated: recipe -> [H, W, 3] sheet, or None.
KnownSheets = Callable[[generation.SheetRecipe], "np.ndarray | None"]


def sheet_inputs(context: EditContext, iteration: int) -> generation.SheetInputs:
  """The sheet's inputs (rgb, mask, control assembled on the grid) from the iteration's reference
  tiles."""
  tiles = load_arrays(context.directory.path("reference", "inputs.npz", iteration=iteration),
                      ("render", "control", "mask"))
  return generation.SheetInputs.from_tiles(tiles["render"], tiles["control"], tiles["mask"],
                                           context.layout)


def candidate_path(context: EditContext, recipe: generation.SheetRecipe) -> Path:
  """The preview's candidate sheet of `recipe` (.npz; beside it the .png)."""
  return context.directory.path("preview", "candidates", f"{recipe.file_stem}.npz")


def _candidate_key(context: EditContext) -> str:
  """What a first-iteration candidate depends on: the reference tiles and the generation."""
  return (canonical_json({"reference": context.keys["reference"]})
          + canonical_json(context.generation_key(1)))


def _known_candidates(context: EditContext) -> KnownSheets:
  """Preview candidates made with the current reference tiles and settings."""
  expected = _candidate_key(context)

  def known(recipe: generation.SheetRecipe) -> np.ndarray | None:
    path = candidate_path(context, recipe)
    if not path.is_file():
      return None
    stored = load_arrays(path, ("rgb", "key"))
    return stored["rgb"] if str(stored["key"]) == expected else None

  return known


def preview_recipes(context: EditContext) -> list[generation.SheetRecipe]:
  """The preview's candidates: one recipe per `PreviewConfig.seeds` then `recipes`, duplicates
  dropped."""
  config = context.settings.preview
  texts = [str(seed) for seed in config.seeds] + list(config.recipes)
  return [generation.SheetRecipe.parse(text) for text in dict.fromkeys(texts)]


def preview_settings(context: EditContext) -> dict[str, Any]:
  """The preview stage's key: its recipes and the first iteration's generation settings."""
  return {"recipes": [str(recipe) for recipe in preview_recipes(context)],
          "generation": context.generation_key(1)}


def preview(context: EditContext) -> str:
  """Generates the candidate sheets one at a time (reusing those made with the same tiles and
  settings) into preview/candidates/, redrawing preview.png as each comes; returns the summary
  line."""
  recipes = preview_recipes(context)
  known, key = _known_candidates(context), _candidate_key(context)
  inputs = sheet_inputs(context, 1)
  files.write_image(context.directory.path("preview", "inputs.png"), figures.image_grid(
      [[inputs.rgb, inputs.mask, inputs.control]], [["reference renders", "masks", "control"]]))
  preview_png = context.directory.path("preview", "preview.png")
  shown = {recipe: sheet for recipe in recipes if (sheet := known(recipe)) is not None}

  def draw() -> None:
    """preview.png: every candidate made so far, side by side."""
    files.write_image(preview_png, figures.image_grid(
        [[shown[recipe] for recipe in recipes if recipe in shown]],
        [[f"sheet {recipe}" for recipe in recipes if recipe in shown]]))

  def save(made: dict[generation.SheetRecipe, np.ndarray]) -> None:
    for recipe, sheet in made.items():
      if recipe in recipes:
        path = candidate_path(context, recipe)
        save_arrays(path, rgb=sheet, key=np.asarray(key))
        files.write_image(path.with_suffix(".png"), sheet)
        shown[recipe] = sheet
    draw()
    bar.update(len(made))

  # When the update runs next in this process, the candidates are made in its batches by its
  # sampler, compiled once for both. Otherwise (`signerf preview`) the user waits for the first
  # candidate: they are made one at a time (preview.png shows each as it comes) by a program
  # compiled for a quick start rather than a quick run (less XLA compilation for a slower
  # sheet brings the first candidate sooner; docs/performance.md).
  generator = context.generator(1)
  if "update" not in context.stages_to_run:
    generator = dataclasses.replace(generator, views_per_device=1, winograd_convolutions=False)
  with tqdm.tqdm(total=len(recipes) - len(shown), unit="sheet", desc="preview",
                 disable=not context.progress, dynamic_ncols=True) as bar:
    generation.generate_sheets(generator, inputs, recipes, known, on_batch=save)
  draw()
  return (f"{len(recipes)} candidate sheets ({', '.join(map(str, recipes))}) side by side: "
          f"{preview_png}; pick one with --sheet RECIPE, re-roll tiles with --reroll "
          "SEED/TILE,TILE@NEWSEED")


def sheet_settings(context: EditContext, iteration: int) -> dict[str, Any]:
  """The sheet stage's key: the chosen recipe and the iteration's generation settings."""
  return {"recipe": context.settings.edit.sheet_recipe(iteration),
          "generation": context.generation_key(iteration)}


def generate_sheet(context: EditContext, iteration: int = 1) -> str:
  """Step 5: the chosen sheet (taken from the preview when it made that recipe) in sheet/sheet.npz
  (rgb [H, W, 3] in [0, 1], control, mask, recipe) and sheet.png; returns the summary line."""
  recipe = generation.SheetRecipe.parse(context.settings.edit.sheet_recipe(iteration))
  inputs = sheet_inputs(context, iteration)
  known = _known_candidates(context) if iteration == 1 else (lambda recipe: None)
  reused = known(recipe) is not None
  sheet = generation.generate_sheets(context.generator(iteration), inputs, [recipe],
                                     known)[recipe]
  directory = context.directory.path("sheet", iteration=iteration)
  save_arrays(directory / "sheet.npz", rgb=sheet, control=inputs.control, mask=inputs.mask,
              recipe=np.asarray(str(recipe)))
  files.write_image(directory / "sheet.png", sheet)
  how = "taken from the preview" if reused else "generated"
  return f"sheet {recipe} {how}: {directory / 'sheet.png'}"
