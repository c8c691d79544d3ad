"""The edited image set as a nerfstudio dataset any nerfstudio method can train on.

`write_edited_dataset` writes, next to the standard nerfstudio files of
`data.write_nerfstudio` (images/ holding the edited views, transforms.json with the
cameras in the scene frame and `applied_transform` back to the source frame, masks/ only when
the source dataset had training masks):
  originals/      the source images, frame for frame;
  edit_masks/     the inpainting masks (8-bit; 1 = generated);
  control/        the normalised control depth the diffusion model saw (16-bit, near = 1);
  control_depth/  the control z-depth in scene units as EXR (0 = nothing there);
                  both rendered only around the selection and the update's tile (0 elsewhere);
and, in transforms.json's `signerf.provenance` block, how the edit was made: prompt, seed,
sheet recipe, every setting, the model's path and sha256, and which views were left unedited.
The extra folders are written first and transforms.json last, so an interrupted write leaves no
transforms.json that points at a partial dataset.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np

from signerf_jax import files, ownership
from signerf_jax.data import nerfstudio, nerfstudio_writer
from signerf_jax.data.dataset import Dataset

EXTRA_FOLDERS = {"originals": "originals", "edit_masks": "edit_masks", "control": "control",
                 "control_depth": "control_depth"}


def write_edited_dataset(directory: str | os.PathLike, source: Dataset, edited_images: np.ndarray,
                         masks: np.ndarray, controls: np.ndarray, control_depths: np.ndarray,
                         provenance: dict[str, Any]) -> Path:
  """Writes the edited dataset (see the module docstring); returns the transforms.json path.

  Args:
    source: the source dataset (all views, scene frame).
    edited_images: [N, H, W, 3] in [0, 1], one per source view (unedited views as the source).
    masks: [N, H, W] inpainting masks in [0, 1].
    controls: [N, H, W] normalised control depth in [0, 1].
    control_depths: [N, H, W] control z-depth (+inf where nothing is there).
    provenance: the record stored in transforms.json.
  """
  directory = Path(directory)
  ownership.remove_file(directory / nerfstudio.TRANSFORMS_NAME)
  for index in range(source.num_images):
    name = f"frame_{index:05d}"
    files.write_image(directory / EXTRA_FOLDERS["originals"] / f"{name}.png", source.images[index])
    files.write_image(directory / EXTRA_FOLDERS["edit_masks"] / f"{name}.png", masks[index])
    files.write_image(directory / EXTRA_FOLDERS["control"] / f"{name}.png", controls[index],
                      bit_depth=16)
    depth = np.where(np.isfinite(control_depths[index]), control_depths[index], 0.0)
    files.write_exr(directory / EXTRA_FOLDERS["control_depth"] / f"{name}.exr", depth)
  # Ground truth of the source (depth, object ids) no longer describes the edited images.
  edited = dataclasses.replace(source, images=np.asarray(edited_images, np.float32), depths=None,
                               extras={}, root=str(directory))
  record = dict(provenance)
  record["files"] = {name: f"{folder}/frame_NNNNN.{'exr' if name == 'control_depth' else 'png'}"
                     for name, folder in EXTRA_FOLDERS.items()}
  return nerfstudio_writer.write_nerfstudio(directory, edited, provenance=record)
