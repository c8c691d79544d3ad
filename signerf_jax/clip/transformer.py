"""The transformer both CLIP towers share, how their transformers checkpoints load, and a
loaded tower (`Tower`: config and params, called on a batch).

Each tower (`text`, `vision`) is embeddings, then `num_hidden_layers` pre-norm encoder layers
(LayerNorm -> self-attention -> residual, LayerNorm -> MLP -> residual), then its own pooling and
optional bias-free projection. The layers differ only in the attention mask: causal for text,
none for images. Submodule names follow transformers' so that the weight mapping is mechanical:
`encoder.layers.3.self_attn.q_proj.weight` is Flax `encoder/layers_3/self_attn/q_proj/kernel`
(transposed: torch Linear stores [out, in], Flax Dense [in, out]).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path
from typing import Any, Callable, ClassVar, Mapping

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import traverse_util

from signerf_jax import files
from signerf_jax import safetensors_io
from signerf_jax.errors import InputError

ACTIVATIONS = {
    "quick_gelu": lambda x: x * jax.nn.sigmoid(1.702 * x),  # OpenAI CLIP (SD 1.x, SDXL 1st).
    "gelu": functools.partial(jax.nn.gelu, approximate=False),  # OpenCLIP (SD 2.x, SDXL 2nd).
}


def check_config(config: Any, source: str | os.PathLike | None) -> None:
  """Raises InputError naming the field when a tower's config cannot be built here.

  Args:
    config: a tower config with hidden_act, hidden_size and num_attention_heads.
    source: its config.json, named in errors.
  """
  if config.hidden_act not in ACTIVATIONS:
    raise InputError(f"hidden_act {config.hidden_act!r} is not implemented (supported: "
                     f"{sorted(ACTIVATIONS)})", source, "hidden_act")
  if config.hidden_size % config.num_attention_heads:
    raise InputError(f"hidden_size {config.hidden_size} is not divisible by "
                     f"num_attention_heads {config.num_attention_heads}", source, "hidden_size")


def tower_config(config_class: Any, config: Mapping[str, Any], with_projection: bool | None,
                 projection_architecture: str) -> Any:
  """A tower's config dataclass from a transformers config.json dict: the fields it has (other
  keys, dropout, dtype, ..., are ignored), projecting when `with_projection`, or, for None, when
  `architectures` names `projection_architecture`."""
  if with_projection is None:
    with_projection = projection_architecture in config.get("architectures", ())
  names = {field.name for field in dataclasses.fields(config_class)} - {"with_projection"}
  return config_class(**{name: config[name] for name in names if name in config},
                      with_projection=with_projection)


def layer_norm(config: Any, name: str) -> nn.LayerNorm:
  """A tower's LayerNorm (`config.layer_norm_eps`), its variance computed as torch does."""
  # Two passes, as torch computes it: E[x²] - E[x]² cancels badly on CLIP's large activations.
  return nn.LayerNorm(epsilon=config.layer_norm_eps, use_fast_variance=False, name=name)


class CLIPAttention(nn.Module):
  config: Any
  causal: bool

  @nn.compact
  def __call__(self, hidden: jax.Array) -> jax.Array:
    """[B, L, D] -> [B, L, D]; token i attends to tokens 0..i when causal, else to all."""
    heads = self.config.num_attention_heads
    split = lambda x: x.reshape(*x.shape[:-1], heads, x.shape[-1] // heads)
    query, key, value = (split(nn.Dense(self.config.hidden_size, name=name)(hidden))
                         for name in ("q_proj", "k_proj", "v_proj"))
    attended = jax.nn.dot_product_attention(query, key, value, is_causal=self.causal)
    return nn.Dense(self.config.hidden_size, name="out_proj")(attended.reshape(hidden.shape))


class CLIPMLP(nn.Module):
  config: Any

  @nn.compact
  def __call__(self, hidden: jax.Array) -> jax.Array:
    hidden = nn.Dense(self.config.intermediate_size, name="fc1")(hidden)
    hidden = ACTIVATIONS[self.config.hidden_act](hidden)
    return nn.Dense(self.config.hidden_size, name="fc2")(hidden)


class CLIPEncoderLayer(nn.Module):
  config: Any
  causal: bool

  @nn.compact
  def __call__(self, hidden: jax.Array) -> jax.Array:
    norm = functools.partial(layer_norm, self.config)
    hidden = hidden + CLIPAttention(self.config, self.causal, name="self_attn")(
        norm(name="layer_norm1")(hidden))
    return hidden + CLIPMLP(self.config, name="mlp")(norm(name="layer_norm2")(hidden))


def encoder_shapes(config: Any, prefix: str) -> dict[str, tuple[int, ...]]:
  """transformers tensor name -> PyTorch shape of every encoder layer weight
  (`{prefix}encoder.layers.{i}.*`)."""
  width, inner = config.hidden_size, config.intermediate_size
  shapes = {}
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
  return shapes


def flax_path(name: str) -> tuple[tuple[str, ...], bool]:
  """transformers name (without the tower prefix) -> (Flax parameter path, transpose?) for
  Linear, LayerNorm and Embedding weights."""
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
  return (*module, "kernel"), True


def params_from_tensors(expected_shapes: Callable[[str], Mapping[str, tuple[int, ...]]],
                        tensors: Mapping[str, np.ndarray], tower_prefix: str,
                        source: str | os.PathLike,
                        convert: Callable[[str, np.ndarray], tuple[tuple[str, ...], np.ndarray]]
                        ) -> dict:
  """Flax params from a transformers state dict, after checking every name and shape.

  Args:
    expected_shapes: prefix -> every tensor the tower needs (`{prefix}name` -> torch shape).
    tensors: checkpoint name -> array, with or without `tower_prefix` (e.g. "text_model.").
    tower_prefix: what checkpoints that nest the tower put before its names.
    source: the checkpoint, named in errors.
    convert: (name without prefix, torch array) -> (Flax path, Flax array).
  """
  prefix = tower_prefix if any(name.startswith(tower_prefix) for name in tensors) else ""
  shapes = expected_shapes(prefix)
  # position_ids is a buffer (arange) that older checkpoints saved.
  safetensors_io.check_tensors(shapes, tensors, source,
                               ignore=(f"{prefix}embeddings.position_ids",))
  flat = {}
  for name in shapes:
    path, value = convert(name.removeprefix(prefix), tensors[name])
    flat[path] = jnp.asarray(value)
  return traverse_util.unflatten_dict(flat)


def load_checkpoint(directory: str | os.PathLike, config_class: Any, projection_name: str,
                    with_projection: bool | None,
                    params_from_tensors: Callable[[Any, Mapping[str, np.ndarray], Path], dict]
                    ) -> tuple[Any, dict]:
  """(config, Flax params) of a transformers CLIP tower folder: config.json + model.safetensors.

  Args:
    directory: the model folder.
    config_class: the tower's config dataclass (with `from_dict(raw, source, with_projection)`).
    projection_name: the projection's tensor name.
    with_projection: load the tower with its projection (CLIP*ModelWithProjection); None
      decides from the config's `architectures`, or, when that is absent, from whether the
      weights hold `projection_name`.
    params_from_tensors: the tower's (config, tensors, source) -> Flax params.
  """
  directory = Path(directory)
  config_path = directory / "config.json"
  raw_config = files.read_json(config_path)
  tensors = safetensors_io.read_safetensors(safetensors_io.find_weight_files(directory))
  if with_projection is None and "architectures" not in raw_config:
    with_projection = projection_name in tensors
  config = config_class.from_dict(raw_config, config_path, with_projection)
  return config, params_from_tensors(config, tensors, directory)


@dataclasses.dataclass(frozen=True, eq=False)
class Tower:
  """A loaded tower: its config and Flax params. Calling it on a batch runs the tower's
  compiled forward pass, which a subclass names (`forward(config, params, inputs)`) together
  with the dtype its inputs take."""
  config: Any
  params: Any
  forward: ClassVar[Callable[[Any, Any, jax.Array], Any]]
  input_dtype: ClassVar[Any]

  def __call__(self, inputs) -> Any:
    return self.forward(self.config, self.params, jnp.asarray(inputs, self.input_dtype))
