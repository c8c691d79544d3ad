"""CLIP image tower in Flax, loaded from transformers checkpoints.

`CLIPVisionTransformer` is transformers' `CLIPVisionModel` (and, with `config.with_projection`,
`CLIPVisionModelWithProjection`): a patch-embedding convolution (no bias), a learned class token
prepended to the patches, learned position embeddings, a LayerNorm before the encoder
(transformers' `pre_layrnorm`, sic), pre-norm bidirectional self-attention layers, a LayerNorm on
the class token's final state (`post_layernorm`, the pooled output) and an optional bias-free
projection of it (`visual_projection`, giving `image_embeds`). The encoder layers are the text
tower's (`clip.transformer`) without the causal mask.

Inputs are preprocessed pixels (`clip.preprocessing`), channels last: [B, S, S, 3] with S the
config's image_size (position embeddings are not interpolated to other sizes).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any, Mapping

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from signerf_jax.clip import transformer
from signerf_jax.errors import InputError

# CLIPModel, CLIPVisionModelWithProjection and transformers 4's CLIPVisionModel checkpoints nest
# the tower under this prefix; transformers >= 5 saves CLIPVisionModel without it.
VISION_MODEL_PREFIX = "vision_model."
PROJECTION_NAME = "visual_projection.weight"


@dataclasses.dataclass(frozen=True)
class CLIPVisionConfig:
  """transformers' CLIPVisionConfig fields (same names and defaults) and whether to project."""

  hidden_size: int = 768
  intermediate_size: int = 3072
  projection_dim: int = 512
  num_hidden_layers: int = 12
  num_attention_heads: int = 12
  num_channels: int = 3
  image_size: int = 224
  patch_size: int = 32
  hidden_act: str = "quick_gelu"
  layer_norm_eps: float = 1e-5
  with_projection: bool = False  # CLIPVisionModelWithProjection: also output `image_embeds`.

  @classmethod
  def from_dict(cls, config: Mapping[str, Any], source: str | os.PathLike | None = None,
                with_projection: bool | None = None) -> "CLIPVisionConfig":
    """From a transformers `config.json` (or CLIPConfig's `vision_config`); unknown keys are
    ignored. `with_projection` None reads it from `architectures`."""
    result = transformer.tower_config(cls, config, with_projection,
                                      "CLIPVisionModelWithProjection")
    for field in ("image_size", "patch_size"):
      if not isinstance(getattr(result, field), int):
        raise InputError(f"only square images and patches (an integer) are implemented, got "
                         f"{getattr(result, field)!r}", source, field)
    if result.image_size % result.patch_size:
      raise InputError(f"image_size {result.image_size} is not a multiple of patch_size "
                       f"{result.patch_size}", source, "image_size")
    transformer.check_config(result, source)
    return result

  @property
  def num_positions(self) -> int:
    """Patches plus the class token."""
    return (self.image_size // self.patch_size)**2 + 1


# ----------------------------------------------------------------------------------------------
# Model. Submodule names follow transformers' so that the weight mapping is mechanical.


class CLIPVisionEmbeddings(nn.Module):
  config: CLIPVisionConfig

  @nn.compact
  def __call__(self, pixel_values: jax.Array) -> jax.Array:
    """[B, S, S, C] -> [B, 1 + (S / patch)^2, D]: the class token, then patches row by row."""
    config = self.config
    patch = (config.patch_size,) * 2
    patches = nn.Conv(config.hidden_size, patch, strides=patch, padding="VALID", use_bias=False,
                      name="patch_embedding")(pixel_values)
    patches = patches.reshape(patches.shape[0], -1, config.hidden_size)
    class_embedding = self.param("class_embedding", nn.initializers.normal(1.0),
                                 (config.hidden_size,))
    class_tokens = jnp.broadcast_to(class_embedding, (patches.shape[0], 1, config.hidden_size))
    positions = nn.Embed(config.num_positions, config.hidden_size, name="position_embedding")(
        jnp.arange(config.num_positions))
    return jnp.concatenate([class_tokens, patches], axis=1) + positions


@struct.dataclass
class CLIPVisionOutput:
  """What the image encoder returns (transformers' names).

  Attributes:
    last_hidden_state: [B, L, D] float32, the last layer's output (no final LayerNorm).
    pooled_output: [B, D] the class token's last state after `post_layernorm`.
    image_embeds: [B, projection_dim] projected pooled output; None without projection.
  """

  last_hidden_state: jax.Array
  pooled_output: jax.Array
  image_embeds: jax.Array | None


class CLIPVisionTransformer(nn.Module):
  """transformers' CLIPVisionModel / CLIPVisionModelWithProjection."""

  config: CLIPVisionConfig

  @nn.compact
  def __call__(self, pixel_values: jax.Array) -> CLIPVisionOutput:
    """pixel_values: [B, S, S, num_channels] float32 preprocessed pixels, S = image_size."""
    config = self.config
    expected = (config.image_size, config.image_size, config.num_channels)
    if tuple(pixel_values.shape[1:]) != expected:
      raise ValueError(f"expected pixel_values [B, {', '.join(map(str, expected))}], got "
                       f"{tuple(pixel_values.shape)}")
    hidden = CLIPVisionEmbeddings(config, name="embeddings")(pixel_values)
    hidden = transformer.layer_norm(config, name="pre_layrnorm")(hidden)
    for index in range(config.num_hidden_layers):
      hidden = transformer.CLIPEncoderLayer(config, causal=False, name=f"layers_{index}")(hidden)
    pooled = transformer.layer_norm(config, name="post_layernorm")(hidden[:, 0])
    image_embeds = None
    if config.with_projection:
      image_embeds = nn.Dense(config.projection_dim, use_bias=False,
                              name="visual_projection")(pooled)
    return CLIPVisionOutput(last_hidden_state=hidden, pooled_output=pooled,
                            image_embeds=image_embeds)


@functools.partial(jax.jit, static_argnums=0)
def encode(config: CLIPVisionConfig, params: Any, pixel_values: jax.Array) -> CLIPVisionOutput:
  """The compiled forward pass: [B, S, S, C] preprocessed pixels -> CLIPVisionOutput."""
  return CLIPVisionTransformer(config).apply({"params": params}, pixel_values)


# ----------------------------------------------------------------------------------------------
# Weights.


def expected_shapes(config: CLIPVisionConfig, prefix: str = VISION_MODEL_PREFIX
                    ) -> dict[str, tuple[int, ...]]:
  """transformers tensor name -> PyTorch shape, for every weight the config needs."""
  width, patch = config.hidden_size, config.patch_size
  shapes = {
      f"{prefix}embeddings.class_embedding": (width,),
      f"{prefix}embeddings.patch_embedding.weight": (width, config.num_channels, patch, patch),
      f"{prefix}embeddings.position_embedding.weight": (config.num_positions, width),
  }
  for name in ("pre_layrnorm", "post_layernorm"):
    shapes[f"{prefix}{name}.weight"] = (width,)
    shapes[f"{prefix}{name}.bias"] = (width,)
  shapes.update(transformer.encoder_shapes(config, prefix))
  if config.with_projection:
    shapes[PROJECTION_NAME] = (config.projection_dim, width)
  return shapes


def _to_flax(name: str, value: np.ndarray) -> tuple[tuple[str, ...], np.ndarray]:
  """transformers name (without prefix) and torch array -> Flax path and array."""
  if name == "embeddings.class_embedding":
    return ("embeddings", "class_embedding"), value
  if name == "embeddings.patch_embedding.weight":  # torch [D, C, P, P] -> Flax [P, P, C, D]
    return ("embeddings", "patch_embedding", "kernel"), np.transpose(value, (2, 3, 1, 0))
  # The encoder sits directly under the tower here: encoder.layers.3 -> layers_3.
  path, transpose = transformer.flax_path(name.removeprefix("encoder."))
  return path, value.T if transpose else value


def params_from_tensors(config: CLIPVisionConfig, tensors: Mapping[str, np.ndarray],
                        source: str | os.PathLike) -> dict:
  """Flax params for `config` from the vision tower's tensors of a transformers state dict
  (split a CLIPModel's first; names with or without the `vision_model.` prefix), checked as
  `transformer.params_from_tensors` checks them."""
  return transformer.params_from_tensors(functools.partial(expected_shapes, config), tensors,
                                        VISION_MODEL_PREFIX, source, _to_flax)


class VisionEncoder(transformer.Tower):
  """A loaded image encoder: call it on [B, S, S, C] preprocessed pixels."""
  forward = staticmethod(encode)
  input_dtype = jnp.float32


def load_vision_encoder(directory: str | os.PathLike, with_projection: bool | None = None
                        ) -> VisionEncoder:
  """A CLIPVisionModel folder (config.json + model.safetensors), as
  CLIPVisionModelWithProjection when `with_projection` (None: see
  `transformer.load_checkpoint`)."""
  return VisionEncoder(*transformer.load_checkpoint(directory, CLIPVisionConfig, PROJECTION_NAME,
                                                    with_projection, params_from_tensors))
