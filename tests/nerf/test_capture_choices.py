"""The settings a capture chooses (`training_run.with_capture_choices`): keypoint depth, photo
consistency and a quarter of the distortion loss for a sparse capture (fewer than
`SPARSE_VIEWS` views) of a scene with a background; five times the distortion loss for a
sparse capture of an object on a constant background; otherwise neither prior and the usual
distortion loss; a value given explicitly is kept; a model with an edit region is never sparse."""

import dataclasses

import pytest

from signerf_jax.nerf import capacity, train, training_run


@pytest.mark.parametrize("name, sparse_value, sparse_object_value, otherwise", [
    ("keypoint_depth_weight", train.SPARSE_KEYPOINT_DEPTH_WEIGHT, 0.0, 0.0),
    ("photo_consistency_weight", train.SPARSE_PHOTO_CONSISTENCY_WEIGHT, 0.0, 0.0),
    ("distortion_loss_weight", train.SPARSE_DISTORTION_LOSS_WEIGHT,
     train.SPARSE_OBJECT_DISTORTION_LOSS_WEIGHT, train.DISTORTION_LOSS_WEIGHT),
])
def test_sparse_captures_get_their_values(sphere, name, sparse_value, sparse_object_value,
                                          otherwise):
  on_constant = training_run.build_model(sphere)
  assert on_constant.capacity.background == "constant"
  scene = dataclasses.replace(on_constant, capacity=dataclasses.replace(
      on_constant.capacity, background="last_sample"))  # as a 360-degree capture's
  sparse, dense = sphere.subset(list(range(12))), sphere
  assert dense.num_images >= capacity.SPARSE_VIEWS > sparse.num_images
  chosen = lambda dataset, model=scene, config=train.TrainConfig(): getattr(
      training_run.with_capture_choices(config, dataset, model), name)
  assert chosen(sparse) == sparse_value > 0 and sparse_value != otherwise
  assert chosen(dense) == otherwise
  assert chosen(sparse, on_constant) == sparse_object_value
  assert chosen(dense, on_constant) == otherwise
  assert chosen(sparse, config=train.TrainConfig(**{name: 0.0})) == 0.0
  assert chosen(dense, config=train.TrainConfig(**{name: 0.5})) == 0.5
  region = dataclasses.replace(scene, edit_region=((-0.5,) * 3, (0.5,) * 3))
  assert chosen(sparse, region) == otherwise
