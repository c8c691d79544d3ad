"""Training the default model on a tiny configuration: batches, losses that go down, resuming,
checkpoints, and the convolution gradients training relies on."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.default_model import losses, model, stage_settings, training, training_data
from signerf_jax.diffusion import layers, schedulers
from signerf_jax.errors import InputError

VAE_SETTINGS = stage_settings.VaeStage(num_steps=4, batch_size=4, learning_rate=3e-3,
                                       warmup_steps=1, object_weight=4.0)
DIFFUSION_SETTINGS = dict(sheets_per_batch=2, singles_per_batch=2, learning_rate=2e-3,
                          warmup_steps=1, num_steps=3, caption_dropout=0.0)


@pytest.fixture(scope="module")
def components(tiny_architecture, tiny_training_data):
  """The tiny model with a one-level UNet and ControlNet: still every kind of layer (the middle
  block's cross-attention among them), and its train step compiles in ~20 s instead of ~34."""
  one_level = dataclasses.replace(tiny_architecture, unet_block_out_channels=(16,))
  return model.build(one_level, tiny_training_data.tokenizer.vocab_size)


def test_batches_are_deterministic_per_step(tiny_training_data):
  settings = stage_settings.UNetStage(**DIFFUSION_SETTINGS)
  make = lambda step: training_data.diffusion_batch(
      tiny_training_data, training_data.step_rng(0, "unet", step), 2, 3,
      settings.mask_kind_weights, settings.sheet_mode_weights, 0.5)
  first, again, other = make(7), make(7), make(8)
  for kind in ("sheets", "singles"):
    for name in first[kind]:
      np.testing.assert_array_equal(first[kind][name], again[kind][name])
  assert any(not np.array_equal(first["singles"][name], other["singles"][name])
             for name in first["singles"])
  size = tiny_training_data.layout.tile_height
  assert first["sheets"]["image"].shape == (2, 2 * size, 3 * size, 3)
  assert first["singles"]["control"].shape == (3, size, size, 1)
  assert first["sheets"]["ids"].shape == (2, tiny_training_data.tokenizer.max_length)


def test_caption_dropout_gives_the_empty_prompt(tiny_training_data):
  batch = training_data.diffusion_batch(tiny_training_data, np.random.default_rng(0), 1, 4,
                                        (1, 1, 1, 1, 1), (1, 1, 1), caption_dropout=1.0)
  empty = tiny_training_data.tokenizer.tokenize([""])
  np.testing.assert_array_equal(batch["singles"]["ids"], np.repeat(empty, 4, 0))
  with pytest.raises(InputError, match="mask_kind_weights"):
    training_data.diffusion_batch(tiny_training_data, np.random.default_rng(0), 1, 1, (1, 1),
                                  (1, 1, 1), 0.0)


def test_vae_batch_greys_out_masked_views(tiny_training_data):
  unmasked = training_data.vae_batch(tiny_training_data, np.random.default_rng(3), 6, 0.0)
  masked = training_data.vae_batch(tiny_training_data, np.random.default_rng(3), 6, 1.0)
  assert unmasked["image"].shape == (6, 32, 32, 3) and unmasked["image"].dtype == np.float32
  changed = np.any(masked["image"] != unmasked["image"], axis=-1)
  assert changed.any() and np.all(masked["image"][changed] == training_data.EMPTY_SLOT_GREY)
  # Object pixels: visible ones only (none under the grey), and every view shows its object.
  assert unmasked["object"].shape == (6, 32, 32, 1)
  assert np.all(unmasked["object"].sum(axis=(1, 2, 3)) > 0)
  assert not np.any(masked["object"][..., 0][changed])


@pytest.mark.slow
def test_object_weight_weights_the_reconstruction_of_object_pixels(components,
                                                                   tiny_training_data):
  batch = training_data.vae_batch(tiny_training_data, np.random.default_rng(0), 4, 0.0)
  params = model.init_vae(components, np.random.default_rng(0))
  loss = lambda weight, object_pixels: float(losses.vae_loss_fn(
      components, dataclasses.replace(VAE_SETTINGS, object_weight=weight))(
          params, {}, {**batch, "object": object_pixels}, jax.random.key(0))[0])
  assert loss(5.0, np.zeros_like(batch["object"])) == pytest.approx(loss(1.0, batch["object"]))
  assert loss(5.0, batch["object"]) != pytest.approx(loss(1.0, batch["object"]), rel=1e-4)


@pytest.mark.slow
def test_inpainting_conditioning_follows_diffusers(components):
  """Masked pixels are 0 in [-1, 1] before encoding; the latent mask takes every f-th pixel."""
  vae_params = model.init_vae(components, np.random.default_rng(0))
  image = jax.random.uniform(jax.random.key(0), (1, 8, 8, 3))
  mask = jnp.zeros((1, 8, 8, 1)).at[:, 2:6, 3:8].set(1.0)
  key = jax.random.key(1)
  latents, latent_mask, masked_latents = losses.inpainting_conditioning(
      components, vae_params, image, mask, key)
  np.testing.assert_array_equal(latent_mask[0, ..., 0], mask[0, ::2, ::2, 0])
  # Encoded together in one batch: the masked image is the second half, with the same noise.
  both = losses.encode_latents(components, vae_params, jnp.concatenate(
      [2 * image - 1, (2 * image - 1) * (1 - mask)]), key)
  np.testing.assert_allclose(masked_latents, both[1:], atol=1e-6)
  np.testing.assert_allclose(latents, both[:1], atol=1e-6)


def _loss_goes_down(loss_fn, params, frozen, batch, settings, steps=3):
  """(loss before, loss after `steps` train steps) on `batch`, both with step 0's noise.

  Both come from the train step's own history (one compilation, no separate loss function
  to compile): the first step records the loss of the initial parameters; one more step from a
  state whose step is reset to 0 records the trained parameters' loss with the same key.
  """
  state = training.init_state(params, settings, ("loss", "gradient_norm") + tuple(
      name for name in losses.DIFFUSION_METRICS + losses.VAE_METRICS
      if name in jax.eval_shape(loss_fn, params, frozen, batch, jax.random.key(0))[1]))
  train_step = training.make_train_step(loss_fn, settings)
  for _ in range(steps):
    state = train_step(state, frozen, batch)
  before = float(state.history["loss"][0])
  assert np.isfinite(np.asarray(state.history["gradient_norm"])[:int(state.step)]).all()
  again = train_step(state.replace(step=jnp.zeros_like(state.step)), frozen, batch)
  assert train_step._cache_size() == 1  # pylint: disable=protected-access
  return before, float(again.history["loss"][0])


def test_vae_steps_reduce_the_loss(components, tiny_training_data):
  images = training_data.vae_batch(tiny_training_data, np.random.default_rng(0), 4, 0.3)
  before, after = _loss_goes_down(losses.vae_loss_fn(components, VAE_SETTINGS),
                                  model.init_vae(components, np.random.default_rng(0)), {},
                                  images, VAE_SETTINGS)
  assert after < 0.9 * before


def _diffusion_setup(stage, components, tiny_architecture, tiny_training_data, **overrides):
  """(loss function, params, frozen, batch, settings) of the "unet" (joint with the
  ControlNet), "unet_alone" or "controlnet" stage."""
  settings = (stage_settings.ControlNetStage if stage == "controlnet"
              else stage_settings.UNetStage)(**{**DIFFUSION_SETTINGS, **overrides})
  batch = jax.tree.map(jnp.asarray, training_data.diffusion_batch(
      tiny_training_data, np.random.default_rng(0), 2, 2, settings.mask_kind_weights,
      settings.sheet_mode_weights, 0.0))
  rng = np.random.default_rng(0)
  weights = {"vae": model.init_vae(components, rng), "unet": model.init_unet(components, rng),
             "text_encoder": model.init_text_encoder(components, rng)}
  weights["controlnet"] = model.init_controlnet(components, weights["unet"], rng)
  trained = {"unet": ("unet", "text_encoder", "controlnet"),
             "unet_alone": ("unet", "text_encoder"), "controlnet": ("controlnet",)}[stage]
  params = {name: weights[name] for name in trained}
  frozen = {name: value for name, value in weights.items()
            if name not in trained and (name != "controlnet" or stage != "unet_alone")}
  scheduler = schedulers.scheduler_config(tiny_architecture.scheduler_config())
  return (losses.diffusion_loss_fn(components, scheduler, settings), params, frozen, batch,
          settings)


def _joint_stage_loss_fns(setting, values, components, tiny_architecture, tiny_training_data):
  """(the joint stage's loss function for each value of one setting, then the params, frozen
  weights and batch they share: the setting changes neither)."""
  setups = {value: _diffusion_setup("unet", components, tiny_architecture, tiny_training_data,
                                    **{setting: value}) for value in values}
  _, params, frozen, batch, _ = setups[values[0]]
  return {value: setup[0] for value, setup in setups.items()}, params, frozen, batch


@pytest.mark.slow
@pytest.mark.parametrize("stage", ["unet", "unet_alone", "controlnet"])
def test_diffusion_steps_reduce_the_loss(stage, components, tiny_architecture,
                                         tiny_training_data):
  loss_fn, params, frozen, batch, settings = _diffusion_setup(
      stage, components, tiny_architecture, tiny_training_data)
  before, after = _loss_goes_down(loss_fn, params, frozen, batch, settings)
  assert after < before


def test_object_cells_mark_latent_cells_holding_any_object_pixel():
  pixels = np.zeros((2, 8, 8, 1), np.float32)
  pixels[0, 5, 2] = 1.0
  pixels[1, :4, 4:] = 1.0
  cells = np.asarray(losses.object_cells(jnp.asarray(pixels), (2, 2)))[..., 0]
  np.testing.assert_array_equal(cells, [[[0, 0], [1, 0]], [[0, 1], [0, 0]]])


@pytest.mark.slow
def test_masked_ground_weight_weights_only_masked_cells_without_object(
    components, tiny_architecture, tiny_training_data):
  loss_fns, params, frozen, batch = _joint_stage_loss_fns(
      "masked_ground_loss_weight", (1.0, 4.0), components, tiny_architecture, tiny_training_data)
  # Both weights in one program: XLA compiles their shared forward pass once (21 s against 30).
  both = jax.jit(lambda params, frozen, batch: {
      weight: loss_fn(params, frozen, batch, jax.random.key(2))[0]
      for weight, loss_fn in loss_fns.items()})
  loss = lambda weight, batch: float(both(params, frozen, batch)[weight])
  # The batch's masks cover ground around the objects: weighting it changes the loss ...
  assert any(np.any(np.asarray(part["mask"]) > np.asarray(part["object"]))
             for part in batch.values())
  assert loss(4.0, batch) != pytest.approx(loss(1.0, batch), rel=1e-5)
  # ... and not when every masked cell holds object.
  covered = {kind: dict(part, object=jnp.ones_like(part["object"]))
             for kind, part in batch.items()}
  assert loss(4.0, covered) == pytest.approx(loss(1.0, covered), rel=1e-6)


@pytest.mark.slow
def test_control_dropout_sets_the_controlnet_scale_of_a_share_of_samples_to_zero(
    components, tiny_architecture, tiny_training_data):
  loss_fns, params, frozen, batch = _joint_stage_loss_fns(
      "control_dropout", (0.0, 1.0), components, tiny_architecture, tiny_training_data)
  # Zero convolutions made non-zero, so the ControlNet changes the UNet's output.
  params["controlnet"] = jax.tree.map(lambda value: value + 0.05, params["controlnet"])
  without = dict(params, controlnet=jax.tree.map(jnp.zeros_like, params["controlnet"]))
  # Both dropouts in one program: their shared parts compile once.
  per_part = jax.jit(lambda params: {
      dropout: loss_fn(params, frozen, batch, jax.random.key(3))[1]
      for dropout, loss_fn in loss_fns.items()})
  with_control, zero_control = per_part(params), per_part(without)
  changed = {dropout: [not np.isclose(with_control[dropout][name], zero_control[dropout][name],
                                      rtol=1e-6) for name in ("loss_sheets", "loss_singles")]
             for dropout in loss_fns}
  # Dropout 0: every sample sees the ControlNet (both parts change); 1: no sample does.
  assert all(changed[0.0]) and not any(changed[1.0]), changed


@pytest.mark.slow
def test_resumed_training_equals_uninterrupted(tmp_path, components, tiny_training_data):
  loss_fn = losses.vae_loss_fn(components, VAE_SETTINGS)
  make_batch = lambda step: training_data.vae_batch(
      tiny_training_data, training_data.step_rng(0, "vae", step), 4, 0.3)
  initial = lambda: model.init_vae(components, np.random.default_rng(0))
  run = lambda directory, max_steps: training.run_stage(
      "vae", directory, VAE_SETTINGS, initial, {}, loss_fn, make_batch, losses.VAE_METRICS,
      training.RunBudget(max_steps=max_steps, progress=False))
  straight = run(tmp_path / "straight", None)
  first = run(tmp_path / "resumed", 2)
  assert int(first.step) == 2 and np.isnan(np.asarray(first.history["loss"][2:])).all()
  resumed = run(tmp_path / "resumed", None)
  assert int(resumed.step) == VAE_SETTINGS.num_steps
  same = lambda tree: jax.tree.map(np.asarray, tree)
  for field in ("params", "ema_params", "opt_state", "history"):
    jax.tree.map(np.testing.assert_array_equal, same(getattr(resumed, field)),
                 same(getattr(straight, field)))
  assert training.stage_finished(tmp_path / "resumed", VAE_SETTINGS)
  assert not training.stage_finished(tmp_path / "resumed", dataclasses.replace(
      VAE_SETTINGS, num_steps=5))


def test_checkpoint_restores_into_other_step_counts_and_refuses_another_model(
    tmp_path, components, tiny_architecture):
  params = model.init_vae(components, np.random.default_rng(0))
  state = training.init_state(params, VAE_SETTINGS, losses.VAE_METRICS)
  state = state.replace(step=jnp.asarray(3, jnp.int32), history={
      name: values.at[:3].set(1.0) for name, values in state.history.items()})
  path = tmp_path
  training.save_checkpoint(path, state)
  restored = training.restore_checkpoint(path, state)
  jax.tree.map(np.testing.assert_array_equal, jax.tree.map(np.asarray, restored),
               jax.tree.map(np.asarray, state))
  # A stage given more steps trains on from its checkpoint: the history grows with NaN.
  longer = training.init_state(params, dataclasses.replace(VAE_SETTINGS, num_steps=9),
                               losses.VAE_METRICS)
  extended = training.restore_checkpoint(path, longer)
  assert int(extended.step) == 3
  loss = np.asarray(extended.history["loss"])
  assert loss.shape == (9,) and np.all(loss[:3] == 1.0) and np.isnan(loss[3:]).all()
  # Given fewer steps than it has done, it is finished and keeps every step's metrics.
  shorter = training.init_state(params, dataclasses.replace(VAE_SETTINGS, num_steps=2),
                                losses.VAE_METRICS)
  np.testing.assert_array_equal(
      training.restore_checkpoint(path, shorter).history["loss"], state.history["loss"][:3])
  other = model.build(dataclasses.replace(tiny_architecture, vae_block_out_channels=(8, 24)),
                      8)
  wider = training.init_state(model.init_vae(other, np.random.default_rng(0)), VAE_SETTINGS,
                              losses.VAE_METRICS)
  with pytest.raises(InputError, match="checkpoint"):
    training.restore_checkpoint(path, wider)


@pytest.mark.slow
@pytest.mark.parametrize("function", ["winograd_2x2", "winograd_4x4", "upsample"])
def test_fast_convolutions_take_the_convolution_gradient(function):
  """Training differentiates the fast convolution rewrites through XLA's convolution."""
  key_x, key_k, key_g = jax.random.split(jax.random.key(0), 3)
  x = jax.random.normal(key_x, (2, 8, 8, 64))
  kernel = jax.random.normal(key_k, (3, 3, 64, 64)) / 24
  if function.startswith("winograd"):
    fast = lambda x, kernel: getattr(layers, f"{function}_conv3x3")(x, kernel, jnp.float32)
    reference = lambda x, kernel: layers.xla_conv(x, kernel, 1, 1, jnp.float32)
  else:
    fast = lambda x, kernel: layers.upsample_conv(x, kernel, jnp.float32)
    reference = lambda x, kernel: layers.xla_conv(layers.upsample_nearest(x), kernel, 1, 1,
                                                  jnp.float32)
  output, fast_vjp = jax.vjp(fast, x, kernel)
  expected, reference_vjp = jax.vjp(reference, x, kernel)
  np.testing.assert_allclose(output, expected, atol=1e-4)
  cotangent = jax.random.normal(key_g, output.shape)
  for got, want in zip(fast_vjp(cotangent), reference_vjp(cotangent)):
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-4)
