"""The training settings a capture chooses: what `TrainConfig` leaves None is chosen from the
number of training views, whether the field models a background and whether the photos have
alpha (`with_capture_choices`), as `capacity.derive_capacity` sizes the model from the scene.
"""

from __future__ import annotations

import dataclasses
from typing import TypeVar

from signerf_jax.data.dataset import Dataset
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf.capacity import SPARSE_VIEWS

# A `train.TrainConfig` (train imports this module, for `capture_default`).
Config = TypeVar("Config")

# The distortion loss's weight (`TrainConfig.distortion_loss_weight`), that of sparse captures
# with a background (with photo consistency, which already moves each ray's weight to where the
# photos agree, a quarter gave stitch with 13 views 0.6 dB more held-out) and of sparse objects
# on a constant background (five times gave lego with 12 views 0.3 dB; docs/performance.md).
DISTORTION_LOSS_WEIGHT = 0.002
SPARSE_DISTORTION_LOSS_WEIGHT = 0.0005
SPARSE_OBJECT_DISTORTION_LOSS_WEIGHT = 0.01
# The keypoint depth weight of sparse captures (`TrainConfig.keypoint_depth_weight`): stitch with
# 13 views gained ~3 dB held-out with it (docs/performance.md).
SPARSE_KEYPOINT_DEPTH_WEIGHT = 1.0
# The photo-consistency weight of sparse captures (`TrainConfig.photo_consistency_weight`):
# stitch with 13 views gained ~0.7 dB held-out with it (docs/performance.md).
SPARSE_PHOTO_CONSISTENCY_WEIGHT = 0.1
# (learning_rate, final_learning_rate) of most captures and of sparse objects on a constant
# background. The latter are under-fitted within minutes (their held-out PSNR follows their
# training views' fit): twice the rates gave lego with 12 views 0.1-0.7 dB (docs/performance.md).
LEARNING_RATES = (1e-2, 1e-3)
SPARSE_OBJECT_LEARNING_RATES = (2e-2, 2e-3)


def with_capture_choices(config: Config, dataset: Dataset, model: nerf_model.NerfModel
                         ) -> Config:
  """`config` with the settings it leaves to the capture (None) chosen. A sparse capture
  (fewer than `SPARSE_VIEWS` training views) of a scene whose background the field models
  (360-degree and forward-facing captures) gets keypoint depth, photo consistency and a quarter
  of the distortion loss; a sparse capture of an object on a constant background five times
  the distortion loss and twice the learning rates; any other the usual distortion loss and
  learning rates and neither prior. Photos with alpha carve the visual hull whenever the model
  has an occupancy grid (`can_carve`).
  An object on a constant background is left without keypoints and photo consistency: its
  silhouettes' corners against the background are keypoints of no 3D point (with them lego
  with 12 views lost 1.9 dB), and its occupancy-grid samples (up to `Capacity.march_steps` a
  ray) made each step four times as slow to compare (docs/performance.md). A model with an
  edit region trains the region alone, on its own rays."""
  sparse = dataset.num_images < SPARSE_VIEWS and model.edit_region is None
  with_background = model.capacity.background != "constant"
  priors = sparse and with_background
  rates = SPARSE_OBJECT_LEARNING_RATES if sparse and not with_background else LEARNING_RATES
  distortion = DISTORTION_LOSS_WEIGHT
  if sparse:
    distortion = (SPARSE_DISTORTION_LOSS_WEIGHT if with_background
                  else SPARSE_OBJECT_DISTORTION_LOSS_WEIGHT)
  chosen = {"keypoint_depth_weight": SPARSE_KEYPOINT_DEPTH_WEIGHT if priors else 0.0,
            "photo_consistency_weight": SPARSE_PHOTO_CONSISTENCY_WEIGHT if priors else 0.0,
            "distortion_loss_weight": distortion,
            "learning_rate": rates[0], "final_learning_rate": rates[1],
            "visual_hull": can_carve(dataset, model)}
  return dataclasses.replace(config, **{name: value for name, value in chosen.items()
                                        if getattr(config, name) is None})


def can_carve(dataset: Dataset, model: nerf_model.NerfModel) -> bool:
  """Whether the photos' alpha can carve the model's occupancy grid (`visual_hull`)."""
  return (dataset.alphas is not None and model.capacity.sampler == "occupancy"
          and model.edit_region is None)


# The settings left to the capture that code reads with `capture_default`, and their value for
# most captures.
USUAL_VALUES = {"distortion_loss_weight": DISTORTION_LOSS_WEIGHT,
                "learning_rate": LEARNING_RATES[0], "final_learning_rate": LEARNING_RATES[1]}


def capture_default(config: Config, name: str) -> float:
  """`config.<name>`, or its value for most captures (`USUAL_VALUES`) where the capture has not
  chosen it (a config `with_capture_choices` did not see)."""
  value = getattr(config, name)
  return USUAL_VALUES[name] if value is None else value
