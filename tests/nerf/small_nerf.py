"""A small NeRF model and training config for fast tests, and a way to count XLA compilations."""

from __future__ import annotations

import contextlib
import dataclasses

import jax

from signerf_jax.nerf import capacity, scene_info, train
from signerf_jax.nerf.model import NerfModel


def small_model(dataset) -> NerfModel:
  """The derived capacity, with a batch small enough for fast tests."""
  scene = scene_info.SceneInfo.from_dataset(dataset)
  derived = capacity.derive_capacity(scene)
  return NerfModel(scene, dataclasses.replace(derived, rays_per_batch=1024,
                                              samples_per_batch=8192, mlp_width=32))


SMALL_CONFIG = train.TrainConfig(steps=200, learning_rate=2e-2, warmup_steps=3,
                                 occupancy_update_every=4, occupancy_warmup_steps=32,
                                 checkpoint_every_steps=1000)


@contextlib.contextmanager
def count_compilations():
  """Yields a list that receives one entry per XLA backend compilation in the block."""
  compiled: list[str] = []

  def listener(event: str, duration: float, **kwargs) -> None:
    if event == "/jax/core/compile/backend_compile_duration":
      compiled.append(event)

  jax.monitoring.register_event_duration_secs_listener(listener)
  try:
    yield compiled
  finally:
    jax.monitoring.unregister_event_duration_listener(listener)
