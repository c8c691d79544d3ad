"""CLIP text encoders in Flax, loaded from transformers checkpoints, and prompt encoding.

`CLIPTextTransformer` is transformers' `CLIPTextModel` (and, with `config.with_projection`,
`CLIPTextModelWithProjection`, SDXL's second encoder): token + position embeddings, pre-norm
causal self-attention layers, a final LayerNorm, the pooled output at the end-of-text token and
an optional bias-free projection of it.

`encode_prompt` / `encode_prompt_sdxl` reproduce what diffusers' Stable Diffusion (1.x, 2.x) and
SDXL pipelines feed the UNet, including the unconditional embeddings for classifier-free guidance.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from typing import Any, Mapping, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from flax import traverse_util

from signerf_jax.clip import transformer
from signerf_jax.clip.tokenizer import Tokenizer

# transformers checkpoints of CLIPTextModelWithProjection (and older CLIPTextModel ones) nest the
# transformer under this prefix; transformers >= 5 saves CLIPTextModel without it.
TEXT_MODEL_PREFIX = "text_model."
PROJECTION_NAME = "text_projection.weight"
# The config value before transformers PR #24773: pool at argmax(ids) (eos has the largest id).
LEGACY_EOS_TOKEN_ID = 2


@dataclasses.dataclass(frozen=True)
class CLIPTextConfig:
  """transformers' CLIPTextConfig fields (same names and defaults) and whether to project."""

  vocab_size: int = 49408
  hidden_size: int = 512
  intermediate_size: int = 2048
  num_hidden_layers: int = 12
  num_attention_heads: int = 8
  max_position_embeddings: int = 77
  hidden_act: str = "quick_gelu"
  layer_norm_eps: float = 1e-5
  projection_dim: int = 512
  bos_token_id: int = 49406
  eos_token_id: int = 49407
  pad_token_id: int = 1
  with_projection: bool = False  # CLIPTextModelWithProjection: also output `text_embeds`.

  @classmethod
  def from_dict(cls, config: Mapping[str, Any], source: str | os.PathLike | None = None,
                with_projection: bool | None = None) -> "CLIPTextConfig":
    """From a transformers `config.json`; unknown keys (dropout, dtype, ...) are ignored.

    `with_projection` None reads it from `architectures`.
    """
    result = transformer.tower_config(cls, config, with_projection,
                                      "CLIPTextModelWithProjection")
    transformer.check_config(result, source)
    return result


# ----------------------------------------------------------------------------------------------
# Model. Submodule names follow transformers' so that the weight mapping is mechanical.


class CLIPTextEmbeddings(nn.Module):
  config: CLIPTextConfig

  @nn.compact
  def __call__(self, input_ids: jax.Array) -> jax.Array:
    config = self.config
    tokens = nn.Embed(config.vocab_size, config.hidden_size, name="token_embedding")(input_ids)
    positions = nn.Embed(config.max_position_embeddings, config.hidden_size,
                         name="position_embedding")(jnp.arange(input_ids.shape[-1]))
    return tokens + positions


class CLIPEncoder(nn.Module):
  config: CLIPTextConfig

  @nn.compact
  def __call__(self, hidden: jax.Array) -> tuple[jax.Array, ...]:
    """All hidden states: the input, then each layer's output."""
    states = [hidden]
    for index in range(self.config.num_hidden_layers):
      states.append(transformer.CLIPEncoderLayer(self.config, causal=True,
                                                 name=f"layers_{index}")(states[-1]))
    return tuple(states)


@struct.dataclass
class CLIPTextOutput:
  """What the text encoder returns (transformers' names).

  Attributes:
    last_hidden_state: [B, L, D] float32, after the final LayerNorm.
    hidden_states: num_hidden_layers + 1 arrays [B, L, D]: the embeddings, then each layer's
      output before the final LayerNorm (`hidden_states[-2]` is SDXL's penultimate layer).
    pooled_output: [B, D] `last_hidden_state` at the end-of-text token.
    text_embeds: [B, projection_dim] projected pooled output; None without projection.
  """

  last_hidden_state: jax.Array
  hidden_states: tuple[jax.Array, ...]
  pooled_output: jax.Array
  text_embeds: jax.Array | None


class CLIPTextTransformer(nn.Module):
  """transformers' CLIPTextModel / CLIPTextModelWithProjection."""

  config: CLIPTextConfig

  @nn.compact
  def __call__(self, input_ids: jax.Array) -> CLIPTextOutput:
    """input_ids: [B, L] int32 with L <= max_position_embeddings."""
    config = self.config
    if input_ids.shape[-1] > config.max_position_embeddings:
      raise ValueError(f"{input_ids.shape[-1]} tokens exceed max_position_embeddings "
                       f"{config.max_position_embeddings}")
    hidden_states = CLIPEncoder(config, name="encoder")(
        CLIPTextEmbeddings(config, name="embeddings")(input_ids))
    last = transformer.layer_norm(config, name="final_layer_norm")(hidden_states[-1])
    if config.eos_token_id == LEGACY_EOS_TOKEN_ID:
      eos_position = jnp.argmax(input_ids, axis=-1)
    else:  # The first eos: the pad token may equal eos.
      eos_position = jnp.argmax(input_ids == config.eos_token_id, axis=-1)
    pooled = jnp.take_along_axis(last, eos_position[:, None, None], axis=1)[:, 0]
    text_embeds = None
    if config.with_projection:
      text_embeds = nn.Dense(config.projection_dim, use_bias=False, name="text_projection")(pooled)
    return CLIPTextOutput(last_hidden_state=last, hidden_states=hidden_states,
                          pooled_output=pooled, text_embeds=text_embeds)


@functools.partial(jax.jit, static_argnums=0)
def encode(config: CLIPTextConfig, params: Any, input_ids: jax.Array) -> CLIPTextOutput:
  """The compiled forward pass: [B, L] int32 ids -> CLIPTextOutput."""
  return CLIPTextTransformer(config).apply({"params": params}, input_ids)


# ----------------------------------------------------------------------------------------------
# Weights.


def expected_shapes(config: CLIPTextConfig, prefix: str = TEXT_MODEL_PREFIX
                    ) -> dict[str, tuple[int, ...]]:
  """transformers tensor name -> PyTorch shape, for every weight the config needs."""
  width = config.hidden_size
  shapes = {
      f"{prefix}embeddings.token_embedding.weight": (config.vocab_size, width),
      f"{prefix}embeddings.position_embedding.weight": (config.max_position_embeddings, width),
      f"{prefix}final_layer_norm.weight": (width,),
      f"{prefix}final_layer_norm.bias": (width,),
  }
  shapes.update(transformer.encoder_shapes(config, prefix))
  if config.with_projection:
    shapes[PROJECTION_NAME] = (config.projection_dim, width)
  return shapes


def params_from_tensors(config: CLIPTextConfig, tensors: Mapping[str, np.ndarray],
                        source: str | os.PathLike) -> dict:
  """Flax params for `config` from a transformers state dict (names with or without the
  `text_model.` prefix), checked as `transformer.params_from_tensors` checks them."""
  return transformer.params_from_tensors(functools.partial(expected_shapes, config), tensors,
                                        TEXT_MODEL_PREFIX, source, _to_flax)


def _to_flax(name: str, value: np.ndarray) -> tuple[tuple[str, ...], np.ndarray]:
  path, transpose = transformer.flax_path(name)
  return path, value.T if transpose else value


def tensors_from_params(config: CLIPTextConfig, params: Any, prefix: str = ""
                        ) -> dict[str, np.ndarray]:
  """The inverse of `params_from_tensors`: transformers-named tensors in torch layouts (no
  `text_model.` prefix by default, as transformers >= 5 saves CLIPTextModel)."""
  flat = traverse_util.flatten_dict(params)
  tensors = {}
  for name in expected_shapes(config, prefix):
    path, transpose = transformer.flax_path(name.removeprefix(prefix))
    value = np.asarray(flat[path])
    tensors[name] = np.ascontiguousarray(value.T if transpose else value)
  return tensors


class TextEncoder(transformer.Tower):
  """A loaded text encoder: call it on [B, L] ids to get a CLIPTextOutput."""
  forward = staticmethod(encode)
  input_dtype = jnp.int32


def load_text_encoder(directory: str | os.PathLike, with_projection: bool | None = None
                      ) -> TextEncoder:
  """A `text_encoder/` or `text_encoder_2/` folder (config.json + model.safetensors), as
  CLIPTextModelWithProjection when `with_projection` (None: see `transformer.load_checkpoint`)."""
  return TextEncoder(*transformer.load_checkpoint(directory, CLIPTextConfig, PROJECTION_NAME,
                                                  with_projection, params_from_tensors))


# ----------------------------------------------------------------------------------------------
# Prompt encoding as in diffusers' pipelines.


@struct.dataclass
class PromptEmbeddings:
  """Text conditioning for the UNet (the negative fields are None without guidance).

  Attributes:
    prompt_embeds: [B, 77, D] cross-attention context.
    negative_prompt_embeds: [B, 77, D] unconditional context for classifier-free guidance.
    pooled_prompt_embeds: [B, P] SDXL's pooled text embedding (None for SD 1.x/2.x).
    negative_pooled_prompt_embeds: [B, P] its unconditional counterpart.
  """

  prompt_embeds: jax.Array
  negative_prompt_embeds: jax.Array | None = None
  pooled_prompt_embeds: jax.Array | None = None
  negative_pooled_prompt_embeds: jax.Array | None = None


def _as_batch(texts: str | Sequence[str], batch_size: int | None = None) -> list[str]:
  """A list of prompts; a single string is repeated to `batch_size`."""
  if isinstance(texts, str):
    return [texts] * (batch_size or 1)
  texts = list(texts)
  if batch_size is not None and len(texts) != batch_size:
    raise ValueError(f"{len(texts)} negative prompts for {batch_size} prompts")
  return texts


def encode_prompt(tokenizer: Tokenizer, text_encoder: TextEncoder, prompts: str | Sequence[str],
                  negative_prompts: str | Sequence[str] | None = None,
                  guidance: bool = True) -> PromptEmbeddings:
  """Stable Diffusion 1.x / 2.x: the last hidden state (after the final LayerNorm).

  Without negative prompts the unconditional embedding is that of the empty prompt.
  """
  prompts = _as_batch(prompts)
  embeddings = text_encoder(tokenizer.tokenize(prompts)).last_hidden_state
  if not guidance:
    return PromptEmbeddings(embeddings)
  negative_prompts = _as_batch("" if negative_prompts is None else negative_prompts, len(prompts))
  negative = text_encoder(tokenizer.tokenize(negative_prompts)).last_hidden_state
  return PromptEmbeddings(embeddings, negative)


def _sdxl_embeddings(tokenizers, text_encoders, prompt_lists) -> tuple[jax.Array, jax.Array]:
  """Penultimate hidden states of all encoders side by side, and the first projected pool."""
  states, pooled = [], None
  for prompts, tokenizer, text_encoder in zip(prompt_lists, tokenizers, text_encoders):
    output = text_encoder(tokenizer.tokenize(prompts))
    states.append(output.hidden_states[-2])
    if pooled is None and output.text_embeds is not None:
      pooled = output.text_embeds
  if pooled is None:
    raise ValueError("SDXL needs a text encoder with projection (CLIPTextModelWithProjection)")
  return jnp.concatenate(states, axis=-1), pooled


def encode_prompt_sdxl(tokenizers: Sequence[Tokenizer], text_encoders: Sequence[TextEncoder],
                       prompts: str | Sequence[str], prompts_2: str | Sequence[str] | None = None,
                       negative_prompts: str | Sequence[str] | None = None,
                       negative_prompts_2: str | Sequence[str] | None = None,
                       guidance: bool = True, force_zeros_for_empty_prompt: bool = True
                       ) -> PromptEmbeddings:
  """SDXL: penultimate hidden states of both encoders concatenated, pooled from the second.

  Args:
    tokenizers, text_encoders: (tokenizer, tokenizer_2) and (text_encoder, text_encoder_2); a
      refiner's single second encoder also works, as in diffusers.
    prompts, prompts_2: prompts for the first and second encoder (prompts_2 defaults to prompts).
    negative_prompts, negative_prompts_2: likewise for the unconditional branch.
    guidance: also compute the unconditional embeddings.
    force_zeros_for_empty_prompt: the pipeline option (`model_index.json`; True for SDXL base):
      without negative prompts the unconditional embeddings are zeros, not the empty prompt's.
  """
  prompts = _as_batch(prompts)
  prompts_2 = _as_batch(prompts_2 or prompts, len(prompts))
  embeddings, pooled = _sdxl_embeddings(tokenizers, text_encoders, (prompts, prompts_2))
  if not guidance:
    return PromptEmbeddings(embeddings, pooled_prompt_embeds=pooled)
  if negative_prompts is None and force_zeros_for_empty_prompt:
    negative, negative_pooled = jnp.zeros_like(embeddings), jnp.zeros_like(pooled)
  else:
    negative_prompts = _as_batch(negative_prompts or "", len(prompts))
    negative_prompts_2 = _as_batch(negative_prompts_2 or negative_prompts, len(prompts))
    negative, negative_pooled = _sdxl_embeddings(tokenizers, text_encoders,
                                                 (negative_prompts, negative_prompts_2))
  return PromptEmbeddings(embeddings, negative, pooled, negative_pooled)
