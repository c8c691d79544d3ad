"""The default model's training losses, one per stage (`stages`).

  "vae"         the AutoencoderKL on 64-pixel views: L1 + L2 reconstruction (object pixels
                can be weighted up: they fill a few percent of a view, yet their colour is what
                a prompt asks for), an L1 on image gradients (edges; no pretrained perceptual
                network exists here) and a small KL term towards N(0, 1). Afterwards its
                latents' standard deviation sets the scaling factor that brings them to unit
                variance.
  "unet"        the 9-channel inpainting UNet, the text encoder and (with `joint_controlnet`)
                the ControlNet together, on latents of the frozen VAE: noisy latents + mask
                (downsampled as diffusers does) + masked-image latents, diffusers' conventions
                (masked image = image in [-1, 1] with the masked pixels 0); loss on the
                scheduler's prediction type (epsilon or v), optionally Min-SNR-gamma weighted
                (Hang et al. 2023), with more weight on masked latents. Each sample gets the
                ControlNet at scale 1, or at scale 0 with probability `control_dropout`, so
                the UNet alone stays a complete model (scale 0 ignores the depth) and the
                ControlNet learns what depth adds (scale 1 follows it). Trained this way, the
                ControlNet clearly lowered the masked selection-region v-loss; added afterwards
                to a frozen UNet through its zero convolutions (the shipped model's first
                recipe), it had not moved the loss after half as many steps.
  "controlnet"  optional: the ControlNet alone on the normalised control depth, everything else
                frozen (ControlNet training as its paper does it, e.g. for a new control).

A loss function is `loss(params, frozen, batch, key) -> (loss, metrics)` (`LossFunction`): the
trained parameters, the frozen ones, the step's batch (`training_data`) and the step's key.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp

from signerf_jax.clip import text as clip_text
from signerf_jax.default_model import model as model_lib
from signerf_jax.default_model import stage_settings
from signerf_jax.diffusion import schedulers

Params = Any
LossFunction = Callable[[Params, Params, Any, jax.Array], tuple[jax.Array, dict[str, jax.Array]]]
# The metrics each stage records: its loss function's, and the train step's loss and gradient norm.
VAE_METRICS = ("loss", "gradient_norm", "l1", "l2", "gradient_l1", "kl")
DIFFUSION_METRICS = ("loss", "gradient_norm", "loss_sheets", "loss_singles")


def image_gradient_l1(prediction: jax.Array, target: jax.Array) -> jax.Array:
  """Mean L1 between the horizontal and vertical finite differences of [B, H, W, C] images."""
  differences = lambda x, axis: jnp.diff(x, axis=axis)
  return (jnp.mean(jnp.abs(differences(prediction, 1) - differences(target, 1)))
          + jnp.mean(jnp.abs(differences(prediction, 2) - differences(target, 2))))


def vae_loss_fn(components: model_lib.Components, settings: stage_settings.VaeStage
                ) -> LossFunction:
  """loss(params, frozen (unused), `training_data.vae_batch` dict, key); metrics unweighted."""
  vae = components.vae

  def loss_fn(params, frozen, batch, key):
    del frozen
    target = 2.0 * batch["image"] - 1.0
    pixel_weights = 1.0 + (settings.object_weight - 1.0) * batch["object"]
    weighted_mean = lambda values: jnp.sum(pixel_weights * values) / (
        jnp.sum(pixel_weights) * values.shape[-1])
    posterior = vae.apply({"params": params}, target, method=vae.encode)
    reconstruction = vae.apply({"params": params}, posterior.sample(key), method=vae.decode)
    error = reconstruction - target
    kl = 0.5 * jnp.mean(jnp.square(posterior.mean) + jnp.exp(posterior.logvar) - 1.0
                        - posterior.logvar)
    metrics = {"l1": jnp.mean(jnp.abs(error)), "l2": jnp.mean(jnp.square(error)),
               "gradient_l1": image_gradient_l1(reconstruction, target), "kl": kl}
    loss = (weighted_mean(jnp.abs(error)) + weighted_mean(jnp.square(error))
            + settings.gradient_weight * metrics["gradient_l1"] + settings.kl_weight * kl)
    return loss, metrics

  return loss_fn


def encode_latents(components: model_lib.Components, vae_params: Params, images: jax.Array,
                   key: jax.Array) -> jax.Array:
  """[B, H, W, 3] images in [-1, 1] -> [B, H/f, W/f, C] diffusion latents (posterior samples)."""
  vae = components.vae
  posterior = vae.apply({"params": vae_params}, images, method=vae.encode)
  return vae.config.to_diffusion_latents(posterior.sample(key))


def inpainting_conditioning(components: model_lib.Components, vae_params: Params,
                            image: jax.Array, mask: jax.Array, key: jax.Array):
  """The clean latents and the UNet's extra channels, as diffusers' inpainting pipelines make them.

  Args:
    image: [B, H, W, 3] in [0, 1]; mask: [B, H, W, 1] in [0, 1] (binarised at 0.5).
  Returns:
    latents [B, h, w, C]; mask [B, h, w, 1] (nearest: every f-th pixel, as torch's interpolate);
    masked-image latents [B, h, w, C] (the image in [-1, 1] with masked pixels 0).
  """
  factor = 2 ** (len(components.vae.config.block_out_channels) - 1)
  image = 2.0 * image - 1.0
  keep = (mask < 0.5).astype(jnp.float32)
  latents = encode_latents(components, vae_params, jnp.concatenate([image, image * keep]), key)
  latents, masked_latents = jnp.split(jax.lax.stop_gradient(latents), 2)
  return latents, (1.0 - keep)[:, ::factor, ::factor], masked_latents


def object_cells(object_pixels: jax.Array, latent_shape: tuple[int, int]) -> jax.Array:
  """[B, h, w, 1] 1 where a latent cell's block of pixels holds any object pixel.

  Args:
    object_pixels: [B, H, W, 1] in {0, 1}, H and W multiples of h and w.
  """
  batch, height, width, _ = object_pixels.shape
  blocks = object_pixels.reshape(batch, latent_shape[0], height // latent_shape[0],
                                 latent_shape[1], width // latent_shape[1], 1)
  return blocks.max(axis=(2, 4))


def diffusion_loss_fn(components: model_lib.Components, scheduler: schedulers.SchedulerConfig,
                      settings: stage_settings.DiffusionStage) -> LossFunction:
  """loss(params, frozen, {"sheets": part, "singles": part}, key) of the UNet or ControlNet stage.

  params: the trained parts of {"unet", "text_encoder", "controlnet"}; frozen: the others and
  "vae". The ControlNet takes part when either holds it, at a per-sample scale of 1 or (with
  probability `settings.control_dropout`) 0. A part is `training_data.diffusion_batch`'s dict;
  the loss is the mean over all samples of both parts.
  """
  alphas_cumprod = jnp.asarray(schedulers.alphas_cumprod(scheduler))
  text_module = clip_text.CLIPTextTransformer(components.text)

  def part_losses(weights, part, key):
    noise_key, time_key, latent_key, dropout_key = jax.random.split(key, 4)
    latents, mask, masked_latents = inpainting_conditioning(
        components, weights["vae"], part["image"], part["mask"], latent_key)
    batch = latents.shape[0]
    context = text_module.apply({"params": weights["text_encoder"]}, part["ids"]).last_hidden_state
    timesteps = jax.random.randint(time_key, (batch,), 0, scheduler.num_train_timesteps)
    noise = jax.random.normal(noise_key, latents.shape)
    alpha_cumprod = alphas_cumprod[timesteps][:, None, None, None]
    alpha, sigma = jnp.sqrt(alpha_cumprod), jnp.sqrt(1.0 - alpha_cumprod)
    noisy = alpha * latents + sigma * noise
    control = None
    if "controlnet" in weights:
      control_image = jnp.repeat(part["control"], model_lib.CONTROL_CHANNELS, axis=-1)
      control = components.controlnet.apply({"params": weights["controlnet"]}, noisy, timesteps,
                                            context, control_image, 1.0)
      kept = jax.random.bernoulli(dropout_key, 1.0 - settings.control_dropout, (batch, 1, 1, 1))
      control = jax.tree.map(lambda residual: residual * kept, control)
    prediction = components.unet.apply(
        {"params": weights["unet"]}, jnp.concatenate([noisy, mask, masked_latents], -1),
        timesteps, context, control=control)
    if scheduler.prediction_type == "v_prediction":
      target = alpha * noise - sigma * latents
    else:
      target = noise
    masked_ground = mask * (1.0 - object_cells(part["object"], mask.shape[1:3]))
    cell_weights = ((1.0 + (settings.masked_loss_weight - 1.0) * mask)
                    * (1.0 + (settings.masked_ground_loss_weight - 1.0) * masked_ground))
    squared = jnp.sum(cell_weights * jnp.square(prediction - target), axis=(1, 2, 3))
    per_sample = squared / (jnp.sum(cell_weights, axis=(1, 2, 3)) * latents.shape[-1])
    if settings.min_snr_gamma > 0:
      snr = alpha_cumprod[:, 0, 0, 0] / (1.0 - alpha_cumprod[:, 0, 0, 0])
      clipped = jnp.minimum(snr, settings.min_snr_gamma)
      per_sample = per_sample * (clipped / (snr + 1.0) if scheduler.prediction_type ==
                                 "v_prediction" else clipped / snr)
    return per_sample

  def loss_fn(params, frozen, batch, key):
    weights = {**frozen, **params}
    losses = {kind: part_losses(weights, batch[kind], jax.random.fold_in(key, index))
              for index, kind in enumerate(("sheets", "singles"))}
    total = jnp.concatenate([losses["sheets"], losses["singles"]]).mean()
    return total, {"loss_sheets": losses["sheets"].mean(),
                   "loss_singles": losses["singles"].mean()}

  return loss_fn
