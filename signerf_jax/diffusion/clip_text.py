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
from pathlib import Path
from typing import Any, Mapping, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from flax import traverse_util

from signerf_jax import files
from signerf_jax.diffusion import safetensors_io
from signerf_jax.diffusion.tokenizer import Tokenizer
from signerf_jax.errors import InputError

ACTIVATIONS = {
    "quick_gelu": lambda x: x * jax.nn.sigmoid(1.702 * x),  # OpenAI CLIP (SD 1.x, SDXL 1st).
    "gelu": functools.partial(jax.nn.gelu, approximate=False),  # OpenCLIP (SD 2.x, SDXL 2nd).
}
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
    if with_projection is None:
      with_projection = "CLIPTextModelWithProjection" in config.get("architectures", ())
    names = {field.name for field in dataclasses.fields(cls)} - {"with_projection"}
    result = cls(**{name: config[name] for name in names if name in config},
                 with_projection=with_projection)
    if result.hidden_act not in ACTIVATIONS:
      raise InputError(f"hidden_act {result.hidden_act!r} is not implemented (supported: "
                       f"{sorted(ACTIVATIONS)})", source, "hidden_act")
    if result.hidden_size % result.num_attention_heads:
      raise InputError(f"hidden_size {result.hidden_size} is not divisible by "
                       f"num_attention_heads {result.num_attention_heads}", source, "hidden_size")
    return result


# ----------------------------------------------------------------------------------------------
# Model. Submodule names follow transformers' so that the weight mapping is mechanical.


def layer_norm(config: CLIPTextConfig, name: str) -> nn.LayerNorm:
  # Two-pass variance as torch computes it: E[x²] - E[x]² cancels badly on CLIP's large
  # activations.
  return nn.LayerNorm(epsilon=config.layer_norm_eps, use_fast_variance=False, name=name)


class CLIPAttention(nn.Module):
  config: CLIPTextConfig

  @nn.compact
  def __call__(self, hidden: jax.Array) -> jax.Array:
    """[B, L, D] -> [B, L, D]; token i attends to tokens 0..i."""
    heads = self.config.num_attention_heads
    split = lambda x: x.reshape(*x.shape[:-1], heads, x.shape[-1] // heads)
    query, key, value = (split(nn.Dense(self.config.hidden_size, name=name)(hidden))
                         for name in ("q_proj", "k_proj", "v_proj"))
    attended = jax.nn.dot_product_attention(query, key, value, is_causal=True)
    return nn.Dense(self.config.hidden_size, name="out_proj")(attended.reshape(hidden.shape))


class CLIPMLP(nn.Module):
  config: CLIPTextConfig

  @nn.compact
  def __call__(self, hidden: jax.Array) -> jax.Array:
    hidden = nn.Dense(self.config.intermediate_size, name="fc1")(hidden)
    hidden = ACTIVATIONS[self.config.hidden_act](hidden)
    return nn.Dense(self.config.hidden_size, name="fc2")(hidden)


class CLIPEncoderLayer(nn.Module):
  config: CLIPTextConfig

  @nn.compact
  def __call__(self, hidden: jax.Array) -> jax.Array:
    norm = functools.partial(layer_norm, self.config)
    hidden = hidden + CLIPAttention(self.config, name="self_attn")(norm(name="layer_norm1")(hidden))
    return hidden + CLIPMLP(self.config, name="mlp")(norm(name="layer_norm2")(hidden))


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
      states.append(CLIPEncoderLayer(self.config, name=f"layers_{index}")(states[-1]))
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
    last = layer_norm(config, name="final_layer_norm")(hidden_states[-1])
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
  width, inner = config.hidden_size, config.intermediate_size
  shapes = {
      f"{prefix}embeddings.token_embedding.weight": (config.vocab_size, width),
      f"{prefix}embeddings.position_embedding.weight": (config.max_position_embeddings, width),
      f"{prefix}final_layer_norm.weight": (width,),
      f"{prefix}final_layer_norm.bias": (width,),
  }
  for index in range(config.num_hidden_layers):
    layer = f"{prefix}encoder.layers.{index}."
    for name in ("q_proj", "k_proj", "v_proj", "out_proj"):
      shapes[f"{layer}self_attn.{name}.weight"] = (width, width)
      shapes[f"{layer}self_attn.{name}.bias"] = (width,)
    for name in ("layer_norm1", "layer_norm2"):
      shapes[f"{layer}{name}.weight"] = (width,)
      shapes[f"{layer}{name}.bias"] = (width,)
    shapes[f"{layer}mlp.fc1.weight"] = (inner, width)
    shapes[f"{layer}mlp.fc1.bias"] = (inner,)
    shapes[f"{layer}mlp.fc2.weight"] = (width, inner)
    shapes[f"{layer}mlp.fc2.bias"] = (width,)
  if config.with_projection:
    shapes[PROJECTION_NAME] = (config.projection_dim, width)
  return shapes


def _flax_path(name: str) -> tuple[tuple[str, ...], bool]:
  """transformers name (without prefix) -> (Flax parameter path, transpose?)."""
  parts = name.split(".")
  module, leaf = parts[:-1], parts[-1]
  if "layers" in module:  # encoder.layers.3 -> encoder/layers_3
    position = module.index("layers")
    module[position:position + 2] = [f"layers_{module[position + 1]}"]
  if leaf == "bias":
    return (*module, "bias"), False
  if module[-1].endswith("embedding"):
    return (*module, "embedding"), False
  if "norm" in module[-1]:
    return (*module, "scale"), False
  return (*module, "kernel"), True  # torch Linear stores [out, in]; Flax Dense [in, out].


def params_from_tensors(config: CLIPTextConfig, tensors: Mapping[str, np.ndarray],
                        source: str | os.PathLike) -> dict:
  """Flax params from a transformers state dict, after checking every name and shape.

  Args:
    config: the model the tensors must fit.
    tensors: checkpoint name -> array, with or without the `text_model.` prefix.
    source: the checkpoint, named in errors.
  """
  prefix = TEXT_MODEL_PREFIX if any(name.startswith(TEXT_MODEL_PREFIX) for name in tensors) else ""
  shapes = expected_shapes(config, prefix)
  # position_ids is a buffer (arange) that older checkpoints saved.
  safetensors_io.check_tensors(shapes, tensors, source,
                               ignore=(f"{prefix}embeddings.position_ids",))
  flat = {}
  for name in shapes:
    path, transpose = _flax_path(name.removeprefix(prefix))
    value = tensors[name]
    flat[path] = jnp.asarray(value.T if transpose else value)
  return traverse_util.unflatten_dict(flat)


def tensors_from_params(config: CLIPTextConfig, params: Any, prefix: str = ""
                        ) -> dict[str, np.ndarray]:
  """The inverse of `params_from_tensors`: transformers-named tensors in torch layouts (no
  `text_model.` prefix by default, as transformers >= 5 saves CLIPTextModel)."""
  flat = traverse_util.flatten_dict(params)
  tensors = {}
  for name in expected_shapes(config, prefix):
    path, transpose = _flax_path(name.removeprefix(prefix))
    value = np.asarray(flat[path])
    tensors[name] = np.ascontiguousarray(value.T if transpose else value)
  return tensors


@dataclasses.dataclass(frozen=True, eq=False)
class TextEncoder:
  """A loaded text encoder: call it on [B, L] ids to get a CLIPTextOutput."""

  config: CLIPTextConfig
  params: Any

  def __call__(self, input_ids) -> CLIPTextOutput:
    return encode(self.config, self.params, jnp.asarray(input_ids, jnp.int32))


def load_text_encoder(directory: str | os.PathLike, with_projection: bool | None = None
                      ) -> TextEncoder:
  """A `text_encoder/` or `text_encoder_2/` folder: config.json + model.safetensors.

  Args:
    directory: the component folder.
    with_projection: load as CLIPTextModelWithProjection; None decides from the config's
      `architectures`, or, when that is absent, from whether the weights hold a projection.
  """
  directory = Path(directory)
  config_path = directory / "config.json"
  raw_config = files.read_json(config_path)
  if not isinstance(raw_config, dict):
    raise InputError("expected a JSON object", config_path)
  tensors = safetensors_io.read_safetensors(safetensors_io.find_weight_files(directory))
  if with_projection is None and "architectures" not in raw_config:
    with_projection = PROJECTION_NAME in tensors
  config = CLIPTextConfig.from_dict(raw_config, config_path, with_projection)
  return TextEncoder(config, params_from_tensors(config, tensors, directory))


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
