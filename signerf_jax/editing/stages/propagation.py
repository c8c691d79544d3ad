"""The update and dataset stages (paper, Sec. 3 step 6, "Image Set Update"): every training view
that shows the selection is inpainted in the empty slot of the sheet (or, for comparisons, on its
own, or not at all: `UpdateConfig.propagation`), and the edited views are written as a nerfstudio
dataset with the masks, control depth and provenance alongside."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from signerf_jax import camera as camera_lib
from signerf_jax import files
from signerf_jax.editing import conditioning as conditioning_lib
from signerf_jax.editing import edited_dataset
from signerf_jax.editing import sheet as sheet_lib
from signerf_jax.editing import update as update_lib
from signerf_jax.editing.config import as_json
from signerf_jax.editing.project import directory_fingerprint, load_arrays
from signerf_jax.editing.stages.context import EditContext, load_conditioning
from signerf_jax.editing.stages.reference import cameras_from_json
from signerf_jax.nerf import render

REFERENCE_VIEWS = "reference_views"


def update_settings(context: EditContext, iteration: int) -> dict[str, Any]:
  """The update stage's key: the seed, the generation, the propagation and the slot crops."""
  config = context.settings.sheet
  return {"seed": context.settings.edit.seed, "generation": context.generation_key(iteration),
          "propagation": context.settings.update.propagation, "crops": config.crops,
          "crop_margin": config.crop_margin, "crop_max_upscale": config.crop_max_upscale}


def _view_loader(context: EditContext, iteration: int):
  """indices -> `update.SlotViews` of those training views (images, masks, control, boxes)."""
  dataset = context.dataset
  boxes = context.tile_boxes(dataset.cameras)
  edited_nerf = context.nerf(iteration - 1) if iteration > 1 else None

  def load_views(indices: np.ndarray) -> update_lib.SlotViews:
    conditioned = [load_arrays(context.view_path(int(index)), ("mask", "control"))
                   for index in indices]
    masks = np.stack([item["mask"] for item in conditioned])
    images = dataset.images[indices]
    if edited_nerf is not None:
      # Iteration 2 updates what the edited NeRF shows in the selection, the photo elsewhere:
      # only the mask's pixels are rendered (0 elsewhere, where the mask weighs nothing).
      rendered = render.render_cameras(edited_nerf.model, edited_nerf.variables,
                                       dataset.cameras.take(indices), pixels=masks > 0)["rgb"]
      images = images * (1 - masks[..., None]) + rendered * masks[..., None]
    return update_lib.SlotViews(images=images, masks=masks,
                                controls=np.stack([item["control"] for item in conditioned]),
                                boxes=boxes[indices])

  return load_views


def update_image_set(context: EditContext, iteration: int = 1) -> str:
  """Step 6: inpaints every training view that shows the selection in the sheet's slot (or alone,
  or none for `reference_views`: `UpdateConfig.propagation`) into update/images/, resuming views
  already done; returns the summary line."""
  sheet = load_arrays(context.directory.path("sheet", "sheet.npz", iteration=iteration),
                      ("rgb", "control"))
  if context.settings.update.propagation == REFERENCE_VIEWS:
    return (f"no view updated (UpdateConfig.propagation = {REFERENCE_VIEWS!r}): the NeRF learns "
            f"the {context.layout.num_tiles} tiles of sheet {sheet['recipe']} at the reference "
            "cameras alone")
  visible = context.visible_views()
  directory = context.directory.path("update", iteration=iteration)
  generator, propagation = context.generator(iteration), context.settings.update.propagation
  edit_batch = update_lib.batch_editor(generator, context.layout, propagation, sheet["rgb"],
                                       sheet["control"])
  report = update_lib.run_update(generator, edit_batch, visible, _view_loader(context, iteration),
                                 directory, context.settings.edit.seed,
                                 progress=context.progress)
  skipped = context.dataset.num_images - len(visible)
  resumed = f", {report['resumed']} done before" if report["resumed"] else ""
  how = (f"in the slot of sheet {sheet['recipe']}" if propagation == "sheet" else
         "each on its own (no sheet)")
  return (f"{len(visible)} views inpainted {how} "
          f"({report['batches']} batches of {report['batch_size']} on {report['devices']} "
          f"device(s){resumed}), {skipped} without the selection left as they are: "
          f"{directory / update_lib.IMAGES_FOLDER}")


def edited_images(context: EditContext, iteration: int, indices: np.ndarray) -> np.ndarray:
  """[len(indices), H, W, 3] float32 in [0, 1]: the update stage's images of those views."""
  directory = context.directory.path("update", iteration=iteration)
  images = [files.read_image(update_lib.edited_image_path(directory, int(index)))[..., :3]
            for index in indices]
  return np.stack(images) if images else np.zeros((0, *context.dataset.images.shape[1:]),
                                                  np.float32)


@dataclasses.dataclass(frozen=True)
class EditedViews:
  """The views the NeRF update learns the edit from: the training views that show the selection,
  as the update stage left them, or (`UpdateConfig.propagation = 'reference_views'`) the
  reference views with the sheet's tiles.

  Attributes:
    cameras: K cameras.
    originals: [K, H, W, 3] float32 in [0, 1], the views before the edit.
    edited: [K, H, W, 3] float32 in [0, 1], after it.
    conditioning: their masks and control (`conditioning.Conditioning` of K cameras).
  """

  cameras: camera_lib.Cameras
  originals: np.ndarray
  edited: np.ndarray
  conditioning: conditioning_lib.Conditioning


def edited_views(context: EditContext, iteration: int) -> EditedViews:
  """The `EditedViews` of an iteration (its update and sheet stages done)."""
  if context.settings.update.propagation == REFERENCE_VIEWS:
    reference = load_conditioning(
        context.directory.path("reference", "inputs.npz", iteration=iteration))
    cameras = cameras_from_json(files.read_json(
        context.directory.path("reference", "cameras.json", iteration=iteration)))
    sheet = load_arrays(context.directory.path("sheet", "sheet.npz", iteration=iteration),
                        ("rgb",))
    tiles, _ = sheet_lib.disassemble(sheet["rgb"], context.layout)
    return EditedViews(cameras, reference.render, np.asarray(tiles, np.float32), reference)
  visible = context.visible_views()
  return EditedViews(context.dataset.cameras.take(visible), context.dataset.images[visible],
                     edited_images(context, iteration, visible),
                     context.conditioning_of_views().take(visible))


def _provenance(context: EditContext, iteration: int) -> dict[str, Any]:
  settings, config = context.settings, context.settings.edit
  return {
      "tool": "signerf_jax.editing", "iteration": iteration, "prompt": config.prompt,
      "negative_prompt": config.negative_prompt, "seed": config.seed,
      "sheet": config.sheet_recipe(iteration), "selection": as_json(settings.selection),
      "selection_scene_frame": context.selection.describe(),
      "generation": as_json(settings.generation_options(iteration)),
      "sheet_layout": as_json(settings.sheet), "tile_size": context.tile_size,
      "model": directory_fingerprint(config.model),
      "controlnet": directory_fingerprint(config.controlnet) if config.controlnet else None,
      "source_dataset": context.data_options,
      "original_nerf": str(context.original_run_dir.resolve()),
      "unedited_views": np.setdiff1d(np.arange(context.dataset.num_images),
                                     context.visible_views()).tolist(),
      "gin_config": settings.gin_config,
  }


def write_dataset(context: EditContext, iteration: int = 1) -> str:
  """Writes the edited views (the originals where the selection is not seen; for `reference_views`,
  the sheet's tiles at the reference cameras) as a nerfstudio dataset in dataset/, masks, control
  depth and provenance alongside; returns the summary line."""
  dataset = context.dataset
  directory = context.directory.path("dataset", iteration=iteration)
  if context.settings.update.propagation == REFERENCE_VIEWS:
    views = edited_views(context, iteration)
    dataset = dataclasses.replace(
        dataset, images=views.originals, cameras=views.cameras, alphas=None, masks=None,
        depths=None, extras={},
        image_names=tuple(f"reference_{index}" for index in range(views.cameras.num_cameras)))
    images, conditioned = views.edited, views.conditioning
  else:
    conditioned = context.conditioning_of_views()
    images = dataset.images.copy()
    visible = context.visible_views()
    images[visible] = edited_images(context, iteration, visible)
  transforms = edited_dataset.write_edited_dataset(
      directory, dataset, images, conditioned.mask, conditioned.control,
      conditioned.control_depth, _provenance(context, iteration))
  return (f"{dataset.num_images} views (originals, masks, control depth alongside) in nerfstudio "
          f"format: {transforms}")
