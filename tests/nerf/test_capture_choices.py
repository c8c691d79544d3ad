"""The settings a capture chooses (`capture_choices.with_capture_choices`): keypoint depth,
photo consistency and a quarter of the distortion loss for a sparse capture (fewer than
`SPARSE_VIEWS` views) of a scene with a background; five times the distortion loss and twice
the learning rates for a sparse capture of an object on a constant background; otherwise
neither prior and the usual distortion loss and learning rates; a value given explicitly is
kept; a model with an edit region is never sparse."""

import dataclasses

import pytest

from signerf_jax.nerf import capacity, capture_choices, train, training_run


@pytest.mark.parametrize("name, sparse_value, sparse_object_value, otherwise", [
    ("keypoint_depth_weight", capture_choices.SPARSE_KEYPOINT_DEPTH_WEIGHT, 0.0, 0.0),
    ("photo_consistency_weight", capture_choices.SPARSE_PHOTO_CONSISTENCY_WEIGHT, 0.0, 0.0),
    ("distortion_loss_weight", capture_choices.SPARSE_DISTORTION_LOSS_WEIGHT,
     capture_choices.SPARSE_OBJECT_DISTORTION_LOSS_WEIGHT,
     capture_choices.DISTORTION_LOSS_WEIGHT),
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
      capture_choices.with_capture_choices(config, dataset, model), name)
  assert chosen(sparse) == sparse_value > 0 and sparse_value != otherwise
  assert chosen(dense) == otherwise
  assert chosen(sparse, on_constant) == sparse_object_value
  assert chosen(dense, on_constant) == otherwise
  assert chosen(sparse, config=train.TrainConfig(**{name: 0.0})) == 0.0
  assert chosen(dense, config=train.TrainConfig(**{name: 0.5})) == 0.5
  region = dataclasses.replace(scene, edit_region=((-0.5,) * 3, (0.5,) * 3))
  assert chosen(sparse, region) == otherwise


def test_sparse_objects_train_with_twice_the_learning_rates(sphere):
  on_constant = training_run.build_model(sphere)
  with_background = dataclasses.replace(on_constant, capacity=dataclasses.replace(
      on_constant.capacity, background="last_sample"))
  region = dataclasses.replace(on_constant, edit_region=((-0.5,) * 3, (0.5,) * 3))
  sparse, dense = sphere.subset(list(range(12))), sphere

  def rates(dataset, model, config=train.TrainConfig()):
    chosen = capture_choices.with_capture_choices(config, dataset, model)
    return chosen.learning_rate, chosen.final_learning_rate

  usual = capture_choices.LEARNING_RATES
  sparse_object = capture_choices.SPARSE_OBJECT_LEARNING_RATES
  assert sparse_object == tuple(2 * rate for rate in usual)
  assert rates(sparse, on_constant) == sparse_object
  for dataset, model in ((dense, on_constant), (sparse, with_background),
                         (dense, with_background), (sparse, region)):
    assert rates(dataset, model) == usual
  assert rates(sparse, on_constant, train.TrainConfig(learning_rate=5e-3)) == (
      5e-3, sparse_object[1])
  # A config no capture has seen (an edit's fine-tuning) trains with the usual rates.
  assert float(train.learning_rate(train.TrainConfig(), 1000, 1.0)) == pytest.approx(usual[1])
