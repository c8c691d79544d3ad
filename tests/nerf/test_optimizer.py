"""The NeRF optimiser (`train.make_optimizer`): optax's clipping, Adam and an injected learning
rate scheduled by the progress each step passes, against the formula it replaced."""

import dataclasses

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from small_nerf import count_compilations

from signerf_jax import checkpoints
from signerf_jax.errors import InputError
from signerf_jax.nerf import train

CONFIG = train.TrainConfig(steps=200, learning_rate=2e-2, final_learning_rate=1e-3,
                           warmup_steps=3)
# (steps done, progress) of the steps taken: through the warm-up, then out of step with the
# step count, as a time budget makes progress.
STEPS = [(0, 0.0), (1, 0.3), (2, 0.31), (3, 0.9), (4, 1.0)]


def fresh_state(config: train.TrainConfig) -> train.TrainState:
  """A state over two parameter groups, as the field and a proposal network."""
  key = jax.random.PRNGKey(0)
  params = {"field": {"table": jax.random.normal(key, (64, 2)), "bias": jnp.zeros(3)},
            "proposal_0": {"table": jax.random.normal(jax.random.fold_in(key, 1), (16, 2))}}
  return train.TrainState(jnp.int32(0), {"params": params},
                          train.make_optimizer(config).init(params), key)


def gradients_at(state: train.TrainState, step: int):
  return jax.tree.map(lambda param: jax.random.normal(jax.random.PRNGKey(step), param.shape),
                      state.variables["params"])


@jax.jit
def optimiser_step(state: train.TrainState, gradients, progress) -> train.TrainState:
  variables, optimizer_state = train.apply_gradients(CONFIG, state, gradients, progress)
  return train.TrainState(state.step + 1, variables, optimizer_state, state.key)


def test_learning_rate_warms_up_then_decays_with_progress():
  config = dataclasses.replace(CONFIG, learning_rate=1e-2, final_learning_rate=1e-4,
                               warmup_steps=10)
  rate = lambda step, progress: float(train.learning_rate(config, step, progress))
  assert rate(0, 0.0) == pytest.approx(1e-3)  # 1/10 of the way through the warm-up
  assert rate(9, 0.0) == pytest.approx(1e-2)
  assert rate(500, 0.5) == pytest.approx(1e-3, rel=1e-5)  # halfway: the geometric mean
  assert rate(500, 1.0) == pytest.approx(1e-4, rel=1e-5)
  assert rate(500, 7.0) == pytest.approx(1e-4, rel=1e-5)  # clamped past the end


def test_every_group_moves_by_the_scheduled_rate_times_adams_step_as_before():
  """The formula the optimiser replaced: params - learning_rate(step, progress) * (clipped
  Adam's update), the rate applied by hand to each group."""
  adam = optax.chain(optax.clip_by_global_norm(CONFIG.gradient_clip_norm),
                     optax.scale_by_adam(b1=0.9, b2=0.99, eps=CONFIG.adam_eps))

  @jax.jit
  def former_step(params, adam_state, gradients, step, progress):
    updates, adam_state = adam.update(gradients, adam_state, params)
    rate = train.learning_rate(CONFIG, step, progress)
    return jax.tree.map(lambda param, update: param - rate * update, params, updates), adam_state

  state = fresh_state(CONFIG)
  params, adam_state = state.variables["params"], adam.init(state.variables["params"])
  for step, progress in STEPS:
    gradients = gradients_at(state, step)
    state = optimiser_step(state, gradients, jnp.float32(progress))
    params, adam_state = former_step(params, adam_state, gradients, step, jnp.float32(progress))
    expected_rate = CONFIG.learning_rate * min((step + 1) / 3, 1.0) * (1e-3 / 2e-2)**progress
    np.testing.assert_allclose(train.last_learning_rate(state.optimizer_state), expected_rate,
                               rtol=1e-6)
    for group in ("field", "proposal_0"):
      for new, former in zip(jax.tree.leaves(state.variables["params"][group]),
                             jax.tree.leaves(params[group])):
        np.testing.assert_array_equal(new, former)
  assert int(state.step) == len(STEPS)


def test_a_second_step_at_another_progress_compiles_nothing():
  state = fresh_state(CONFIG)
  state = optimiser_step(state, gradients_at(state, 0), jnp.float32(0.0))
  with count_compilations() as compiled:
    for step, progress in STEPS[1:]:
      state = optimiser_step(state, gradients_at(state, step), jnp.float32(progress))
  assert compiled == []


def test_a_checkpoint_from_before_the_scheduled_optimiser_resumes_as_it_would_have(tmp_path):
  """Older checkpoints hold clipping's and Adam's states only (`train.upgrade_state_dict`)."""
  state = fresh_state(CONFIG)
  for step, progress in STEPS[:2]:
    state = optimiser_step(state, gradients_at(state, step), jnp.float32(progress))
  state_dict = flax.serialization.to_state_dict(jax.device_get(state))
  older = {**state_dict, "optimizer_state": {name: state_dict["optimizer_state"][name]
                                             for name in ("0", "1")}}
  checkpoints.save(tmp_path, older, {"step": 2})
  with pytest.raises(InputError, match="does not match"):
    checkpoints.restore(tmp_path, state)
  restored, _ = checkpoints.restore(tmp_path, state, train.upgrade_state_dict)
  step, progress = STEPS[2]
  continued = optimiser_step(state, gradients_at(state, step), jnp.float32(progress))
  resumed = optimiser_step(restored, gradients_at(restored, step), jnp.float32(progress))
  for new, former in zip(jax.tree.leaves(resumed), jax.tree.leaves(continued)):
    np.testing.assert_array_equal(new, former)
