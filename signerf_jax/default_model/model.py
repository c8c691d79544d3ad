"""The default model's architecture: small components described as diffusers config dicts.

The shipped model is an ordinary diffusers-layout checkpoint of the Stable Diffusion ControlNet
inpainting family, only small, so it runs through exactly the code and loaders that serve real
checkpoints (`signerf_jax.diffusion`):
  vae/           AutoencoderKL with 3 blocks (latent factor 4) and 4 latent channels, no
                 attention (tiles of a sheet are encoded locally, and it is faster);
  text_encoder/  CLIPTextModel, a few narrow layers over the word tokenizer's 16 positions (eos
                 id 3, so pooling takes the first eos);
  unet/          UNet2DConditionModel with 9 input channels (noisy latents, mask, masked-image
                 latents): few levels, cross-attention at the two lower resolutions and a
                 mid block whose self-attention sees the whole latent (all tiles of a sheet);
  controlnet/    ControlNetModel copying the UNet's down path, with a conditioning embedding
                 that downsamples the control image by the latent factor;
  scheduler/     the noise schedule the UNet is trained with.
A 128 x 192 sheet of 64-pixel tiles is a 32 x 48 latent; a single 64-pixel view a 16 x 16 one.

`Architecture` (gin: `default_model_architecture.<field>`) holds the sizes; its methods return
the config dicts exactly as they are written to `<component>/config.json`, and `build` parses
them through the loaders' own config parsers into the Flax modules.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import gin
import jax
import numpy as np
from flax import traverse_util

from signerf_jax.clip import text as clip_text
from signerf_jax.clip import word_tokenizer
from signerf_jax.diffusion import controlnet as controlnet_lib
from signerf_jax.diffusion import model_configs
from signerf_jax.diffusion import unet as unet_lib
from signerf_jax.diffusion import vae as vae_lib
from signerf_jax.diffusion import weights

DIFFUSERS_VERSION = "0.42.1"
TRANSFORMERS_VERSION = "5.23.0"
# The inpainting UNet's input: noisy latents, the mask, the masked image's latents.
INPAINTING_CHANNELS = 2 * 4 + 1
CONTROL_CHANNELS = 3  # A grey control image, as depth ControlNets take it.


@gin.configurable("default_model_architecture")
@dataclasses.dataclass(frozen=True)
class Architecture:
  """Sizes of the default model's components.

  Attributes:
    vae_block_out_channels: AutoencoderKL blocks; n blocks give a latent factor 2^(n - 1).
    vae_layers_per_block: resnets per encoder block (the decoder has one more).
    vae_norm_groups: GroupNorm groups of the VAE.
    latent_channels: latent channels (4, as Stable Diffusion's).
    vae_scaling_factor: multiplies the VAE's latents into the diffusion model's (set after the
      VAE is trained, to 1 / std of the data's latents).
    unet_block_out_channels: UNet levels; the first level has no attention, the others
      cross-attention (with self-attention) in each layer.
    unet_layers_per_block: resnets per down block (up blocks have one more).
    attention_heads: heads in every transformer (diffusers' `attention_head_dim`).
    norm_groups: GroupNorm groups of the UNet and ControlNet.
    conditioning_embedding_channels: the ControlNet's conditioning embedding; n entries
      downsample by 2^(n - 1), which must equal the VAE's latent factor.
    text_hidden_size, text_layers, text_heads, text_intermediate_size: the CLIP text encoder.
    max_text_length: token positions (the word tokenizer's max_length).
    num_train_timesteps, beta_schedule, beta_start, beta_end, prediction_type: the noise
      schedule, in diffusers' scheduler terms.
    scheduler_class: the diffusers scheduler the checkpoint names for sampling.
  """

  vae_block_out_channels: tuple[int, ...] = (32, 64, 64)
  vae_layers_per_block: int = 1
  vae_norm_groups: int = 16
  latent_channels: int = 4
  vae_scaling_factor: float = 1.0
  unet_block_out_channels: tuple[int, ...] = (64, 128, 128)
  unet_layers_per_block: int = 1
  attention_heads: int = 4
  norm_groups: int = 32
  conditioning_embedding_channels: tuple[int, ...] = (16, 32, 64)
  text_hidden_size: int = 64
  text_layers: int = 2
  text_heads: int = 4
  text_intermediate_size: int = 256
  max_text_length: int = word_tokenizer.DEFAULT_MAX_LENGTH
  num_train_timesteps: int = 1000
  beta_schedule: str = "linear"
  beta_start: float = 0.0001
  beta_end: float = 0.02
  prediction_type: str = "v_prediction"
  scheduler_class: str = "DPMSolverMultistepScheduler"

  @property
  def latent_factor(self) -> int:
    """Pixels per latent cell along each axis."""
    return 2 ** (len(self.vae_block_out_channels) - 1)

  def vae_config(self) -> dict[str, Any]:
    """diffusers AutoencoderKL config.json."""
    blocks = len(self.vae_block_out_channels)
    return {"_class_name": "AutoencoderKL", "_diffusers_version": DIFFUSERS_VERSION,
            "in_channels": 3, "out_channels": 3,
            "down_block_types": ["DownEncoderBlock2D"] * blocks,
            "up_block_types": ["UpDecoderBlock2D"] * blocks,
            "block_out_channels": list(self.vae_block_out_channels),
            "layers_per_block": self.vae_layers_per_block, "act_fn": "silu",
            "latent_channels": self.latent_channels, "norm_num_groups": self.vae_norm_groups,
            "sample_size": 64, "scaling_factor": self.vae_scaling_factor,
            "mid_block_add_attention": False, "force_upcast": False}

  def _backbone(self) -> dict[str, Any]:
    levels = len(self.unet_block_out_channels)
    return {"block_out_channels": list(self.unet_block_out_channels),
            "down_block_types": ["DownBlock2D"] + ["CrossAttnDownBlock2D"] * (levels - 1),
            "mid_block_type": "UNetMidBlock2DCrossAttn",
            "layers_per_block": self.unet_layers_per_block,
            "attention_head_dim": self.attention_heads,
            "cross_attention_dim": self.text_hidden_size,
            "norm_num_groups": self.norm_groups, "use_linear_projection": True}

  def unet_config(self) -> dict[str, Any]:
    """diffusers UNet2DConditionModel config.json (9-channel inpainting)."""
    levels = len(self.unet_block_out_channels)
    return {"_class_name": "UNet2DConditionModel", "_diffusers_version": DIFFUSERS_VERSION,
            **self._backbone(), "in_channels": INPAINTING_CHANNELS,
            "out_channels": self.latent_channels,
            "up_block_types": ["CrossAttnUpBlock2D"] * (levels - 1) + ["UpBlock2D"],
            "sample_size": 64 // self.latent_factor}

  def controlnet_config(self) -> dict[str, Any]:
    """diffusers ControlNetModel config.json (4-channel latents, grey depth image)."""
    return {"_class_name": "ControlNetModel", "_diffusers_version": DIFFUSERS_VERSION,
            **self._backbone(), "in_channels": self.latent_channels,
            "conditioning_channels": CONTROL_CHANNELS,
            "conditioning_embedding_out_channels": list(self.conditioning_embedding_channels)}

  def text_encoder_config(self, vocab_size: int) -> dict[str, Any]:
    """transformers CLIPTextModel config.json for a word vocabulary of `vocab_size` tokens."""
    tokenizer = word_tokenizer.WordTokenizer.from_words([], self.max_text_length)
    return {"architectures": ["CLIPTextModel"], "model_type": "clip_text_model",
            "transformers_version": TRANSFORMERS_VERSION,
            "vocab_size": vocab_size, "hidden_size": self.text_hidden_size,
            "intermediate_size": self.text_intermediate_size,
            "num_hidden_layers": self.text_layers, "num_attention_heads": self.text_heads,
            "max_position_embeddings": self.max_text_length, "hidden_act": "quick_gelu",
            "layer_norm_eps": 1e-5, "projection_dim": self.text_hidden_size,
            "bos_token_id": tokenizer.bos_id, "eos_token_id": tokenizer.eos_id,
            "pad_token_id": tokenizer.pad_id}

  def scheduler_config(self) -> dict[str, Any]:
    """diffusers scheduler_config.json of the training noise schedule."""
    return {"_class_name": self.scheduler_class, "_diffusers_version": DIFFUSERS_VERSION,
            "num_train_timesteps": self.num_train_timesteps, "beta_schedule": self.beta_schedule,
            "beta_start": self.beta_start, "beta_end": self.beta_end,
            "prediction_type": self.prediction_type, "timestep_spacing": "trailing",
            "steps_offset": 0, "clip_sample": False, "set_alpha_to_one": False}

  def check(self) -> None:
    """Raises ValueError if the components do not fit together."""
    control_factor = 2 ** (len(self.conditioning_embedding_channels) - 1)
    if control_factor != self.latent_factor:
      raise ValueError(f"the conditioning embedding downsamples by {control_factor}, the VAE by "
                       f"{self.latent_factor}")


@dataclasses.dataclass(frozen=True)
class Components:
  """The Flax modules of the default model (parsed from `Architecture`'s config dicts)."""

  vae: vae_lib.AutoencoderKL
  unet: unet_lib.UNet2DCondition
  controlnet: controlnet_lib.ControlNet
  text: clip_text.CLIPTextConfig


def build(architecture: Architecture, vocab_size: int) -> Components:
  """The modules, configured through the loaders' config parsers (as a saved checkpoint is)."""
  architecture.check()
  return Components(
      vae=vae_lib.AutoencoderKL(model_configs.AutoencoderConfig.from_dict(
          architecture.vae_config(), "vae/config.json")),
      unet=unet_lib.UNet2DCondition(model_configs.UNetConfig.from_dict(
          architecture.unet_config(), "unet/config.json")),
      controlnet=controlnet_lib.ControlNet(model_configs.ControlNetConfig.from_dict(
          architecture.controlnet_config(), "controlnet/config.json")),
      text=clip_text.CLIPTextConfig.from_dict(architecture.text_encoder_config(vocab_size),
                                              "text_encoder/config.json"))


def initial_params(shapes: dict[tuple[str, ...], Any], rng: np.random.Generator) -> dict:
  """Starting parameters for the abstract {Flax path: shape} `shapes`, built in numpy.

  Flax's own initialisers compile one random-number program per parameter, which takes about a
  minute even for a tiny UNet; these are the same rules drawn on the host: kernels
  N(0, 1 / fan_in) (LeCun normal), embeddings N(0, 0.02^2) (CLIP's), norm scales 1, biases 0.
  """
  flat = {}
  for path, leaf in shapes.items():
    shape, name = tuple(leaf.shape), path[-1]
    if name == "kernel":
      value = rng.standard_normal(shape) / np.sqrt(np.prod(shape[:-1]))
    elif name == "embedding":
      value = 0.02 * rng.standard_normal(shape)
    elif name == "scale":
      value = np.ones(shape)
    else:
      value = np.zeros(shape)
    flat[path] = value.astype(np.float32)
  return traverse_util.unflatten_dict(flat)


def init_vae(components: Components, rng: np.random.Generator) -> dict:
  """Starting VAE parameters (`initial_params` for the VAE's shapes)."""
  return initial_params(weights.abstract_params(components.vae), rng)


def init_text_encoder(components: Components, rng: np.random.Generator) -> dict:
  """Starting text-encoder parameters (`initial_params` for the CLIP text transformer's shapes)."""
  ids = jax.ShapeDtypeStruct((1, components.text.max_position_embeddings), np.int32)
  shapes = jax.eval_shape(lambda ids: clip_text.CLIPTextTransformer(components.text).init(
      jax.random.key(0), ids), ids)["params"]
  return initial_params(traverse_util.flatten_dict(shapes), rng)


def init_unet(components: Components, rng: np.random.Generator) -> dict:
  """Starting UNet parameters (`initial_params` for the UNet's shapes)."""
  return initial_params(weights.abstract_params(components.unet), rng)


def init_controlnet(components: Components, unet_params: dict, rng: np.random.Generator) -> dict:
  """A ControlNet starting as ControlNet training does: the UNet's down path and mid block
  copied, the conditioning embedding's last convolution and every output conv zero, so that at
  first it adds nothing to the UNet."""
  params = initial_params(weights.abstract_params(components.controlnet), rng)
  copied = {name: value for name, value in unet_params.items()
            if name.startswith(("down_blocks", "mid_block", "time_embedding"))}
  params = {**params, **jax.tree.map(np.asarray, copied)}
  # The UNet's conv_in also reads the mask and masked-image latents; keep its latent channels.
  latent_channels = params["conv_in"]["kernel"].shape[2]
  params["conv_in"] = {"kernel": np.asarray(unet_params["conv_in"]["kernel"])[:, :, :latent_channels],
                       "bias": np.asarray(unet_params["conv_in"]["bias"])}
  zero = lambda tree: jax.tree.map(np.zeros_like, tree)
  embedding = dict(params["controlnet_cond_embedding"])
  embedding["conv_out"] = zero(embedding["conv_out"])
  params["controlnet_cond_embedding"] = embedding
  for name in params:
    if name.startswith("controlnet_down_blocks") or name == "controlnet_mid_block":
      params[name] = zero(params[name])
  return params


def parameter_count(params) -> int:
  """The number of scalars in a parameter pytree."""
  return int(sum(np.size(leaf) for leaf in jax.tree.leaves(params)))
