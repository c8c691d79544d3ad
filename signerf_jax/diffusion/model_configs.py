"""The configurations of the UNet, ControlNet and AutoencoderKL, parsed from diffusers' config.json.

Each parser takes the JSON dict as diffusers writes it (`save_pretrained`), checks every option
against what this port implements (the tables of `model_options`) and that the options fit
together, and returns a frozen dataclass with per-block values spelled out (tuples, one entry
per down block). What does not fit raises `InputError` naming the config file and the field.

diffusers' historical naming is kept exactly: a UNet's `attention_head_dim` is the *number of
heads* unless `num_attention_heads` is set, and each transformer's head size is then
`block channels // heads` (SD 1.x: 8 heads everywhere; SD 2.x: [5, 10, 20, 20] heads of 64).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, ClassVar, Mapping, Self

from signerf_jax import files
from signerf_jax.diffusion import model_options
from signerf_jax.diffusion.model_options import (CROSS_ATTENTION_DOWN, CROSS_ATTENTION_MID,
                                                 CROSS_ATTENTION_UP, PLAIN_DOWN, PLAIN_MID,
                                                 PLAIN_UP)
from signerf_jax.errors import InputError

@dataclasses.dataclass(frozen=True)
class BackboneConfig:
  """The encoder half shared by UNet2DConditionModel and ControlNetModel.

  Per-block tuples have one entry per down block (the up path uses them reversed, the mid
  block the last entry). `num_attention_heads` is the resolved head count (see module doc).
  `upcast_attention` (SD 2.x) needs no action: attention scores and softmax are float32 here in
  every precision mode, which is what it asks for.
  """
  in_channels: int
  block_out_channels: tuple[int, ...]
  down_block_types: tuple[str, ...]
  layers_per_block: tuple[int, ...]
  transformer_layers_per_block: tuple[int, ...]
  num_attention_heads: tuple[int, ...]
  cross_attention_dim: int
  mid_block_type: str | None
  mid_block_scale_factor: float
  downsample_padding: int
  norm_num_groups: int
  norm_eps: float
  use_linear_projection: bool
  upcast_attention: bool
  flip_sin_to_cos: bool
  freq_shift: float
  time_embedding_dim: int
  addition_embed_type: str | None
  addition_time_embed_dim: int | None
  projection_class_embeddings_input_dim: int | None
  conv_in_kernel: int

  # Set by each model, with `own_fields(options, path) -> dict` (its own fields, after its own
  # checks): its option tables (defaults, supported values; `model_options`) and mid blocks.
  OPTION_TABLES: ClassVar[tuple[Mapping[str, Any], Mapping[str, Any]]]
  MID_BLOCK_TYPES: ClassVar[tuple[str | None, ...]]

  @classmethod
  def from_dict(cls, raw: Mapping[str, Any], path: str | os.PathLike = "config.json") -> Self:
    """The config of diffusers' config.json dict `raw` (`path` is named in errors): the model's
    own options are checked first (`own_fields`), then the shared blocks."""
    path = Path(path)
    options = model_options.read_options(raw, path, *cls.OPTION_TABLES)
    own_fields = cls.own_fields(options, path)
    return cls(**_backbone_fields(options, path, cls.MID_BLOCK_TYPES), **own_fields)


def _check_block_types(options: dict[str, Any], field: str, implemented: tuple[str, str],
                       path: Path) -> None:
  """Raises unless every block type the option `field` lists is one of the two implemented."""
  for block_type in options[field]:
    if block_type not in implemented:
      raise InputError(f"unsupported block type {block_type!r}; this port implements "
                       f"{implemented[0]} and {implemented[1]}", path, field)


def _check_blocks(options: dict[str, Any], path: Path, mid_block_types: tuple) -> None:
  """Raises unless the blocks are ones this port builds: a channel count and a known type per
  down block, a known mid block, norm groups dividing every block's channels, and one
  transformer depth per block."""
  channels = options["block_out_channels"]
  down_types = options["down_block_types"]
  count = len(down_types)
  if not isinstance(channels, tuple) or len(channels) != count:
    raise InputError(f"needs one entry per down block ({count})", path, "block_out_channels")
  _check_block_types(options, "down_block_types", (CROSS_ATTENTION_DOWN, PLAIN_DOWN), path)
  if options["mid_block_type"] not in mid_block_types:
    raise InputError(f"unsupported mid block {options['mid_block_type']!r}; this port implements "
                     f"{' or '.join(map(repr, mid_block_types))}", path, "mid_block_type")
  groups = options["norm_num_groups"]
  if not isinstance(groups, int) or any(c % groups for c in channels):
    raise InputError(f"must be an integer dividing every block's channels {list(channels)}",
                     path, "norm_num_groups")
  transformer_layers = options["transformer_layers_per_block"]
  if isinstance(transformer_layers, tuple) and any(isinstance(v, (list, tuple))
                                                   for v in transformer_layers):
    raise InputError("per-layer lists (asymmetric UNets) are not implemented", path,
                     "transformer_layers_per_block")


def _attention_heads(options: dict[str, Any], count: int, path: Path) -> tuple[int, ...]:
  """Heads per down block: `num_attention_heads` when set, else `attention_head_dim` (see the
  module docstring); each must divide its block's channels."""
  heads_field = "attention_head_dim" if options["num_attention_heads"] is None else \
      "num_attention_heads"
  heads = model_options.per_block(options, heads_field, count, path)
  for block_channels, block_heads in zip(options["block_out_channels"], heads):
    if block_channels % block_heads:
      raise InputError(f"{block_heads} heads do not divide {block_channels} channels", path,
                       heads_field)
  return heads


def _cross_attention_dim(options: dict[str, Any], count: int, path: Path) -> int:
  """The width of the text states, given once or (all equal) per down block."""
  cross_attention_dims = model_options.per_block(options, "cross_attention_dim", count, path)
  if len(set(cross_attention_dims)) != 1:
    raise InputError("a different cross-attention width per block is not implemented", path,
                     "cross_attention_dim")
  return cross_attention_dims[0]


def _backbone_fields(options: dict[str, Any], path: Path, mid_block_types: tuple) -> dict:
  """The `BackboneConfig` fields of a UNet's or ControlNet's options (`read_options`' result),
  after checking that they fit together; `mid_block_types` are the mid blocks allowed."""
  _check_blocks(options, path, mid_block_types)
  count = len(options["down_block_types"])
  heads = _attention_heads(options, count, path)
  cross_attention_dim = _cross_attention_dim(options, count, path)
  if options["addition_embed_type"] == "text_time":
    for name in ("addition_time_embed_dim", "projection_class_embeddings_input_dim"):
      if not isinstance(options[name], int):
        raise InputError("required (an integer) when addition_embed_type is 'text_time'", path,
                         name)
  per_block = lambda name: model_options.per_block(options, name, count, path)
  return dict(
      in_channels=options["in_channels"],
      block_out_channels=options["block_out_channels"],
      down_block_types=options["down_block_types"],
      layers_per_block=per_block("layers_per_block"),
      transformer_layers_per_block=per_block("transformer_layers_per_block"),
      num_attention_heads=heads,
      cross_attention_dim=cross_attention_dim,
      mid_block_type=options["mid_block_type"],
      mid_block_scale_factor=float(options["mid_block_scale_factor"]),
      downsample_padding=options["downsample_padding"],
      norm_num_groups=options["norm_num_groups"],
      norm_eps=float(options["norm_eps"]),
      use_linear_projection=bool(options["use_linear_projection"]),
      upcast_attention=bool(options["upcast_attention"]),
      flip_sin_to_cos=bool(options["flip_sin_to_cos"]),
      freq_shift=float(options["freq_shift"]),
      time_embedding_dim=options.get("time_embedding_dim") or options["block_out_channels"][0] * 4,
      addition_embed_type=options["addition_embed_type"],
      addition_time_embed_dim=options["addition_time_embed_dim"],
      projection_class_embeddings_input_dim=options["projection_class_embeddings_input_dim"],
      conv_in_kernel=options.get("conv_in_kernel", 3),
  )


@dataclasses.dataclass(frozen=True)
class UNetConfig(BackboneConfig):
  """UNet2DConditionModel. The up path mirrors the down path (reversed per-block tuples)."""
  out_channels: int
  up_block_types: tuple[str, ...]
  conv_out_kernel: int
  center_input_sample: bool

  OPTION_TABLES: ClassVar = (model_options.UNET_DEFAULTS, model_options.UNET_FIXED)
  MID_BLOCK_TYPES: ClassVar = (CROSS_ATTENTION_MID, PLAIN_MID, None)

  @classmethod
  def own_fields(cls, options: dict[str, Any], path: Path) -> dict[str, Any]:
    up_types = options["up_block_types"]
    if len(up_types) != len(options["down_block_types"]):
      raise InputError("needs as many entries as down_block_types", path, "up_block_types")
    _check_block_types(options, "up_block_types", (CROSS_ATTENTION_UP, PLAIN_UP), path)
    for name in ("conv_in_kernel", "conv_out_kernel"):
      if options[name] % 2 != 1:
        raise InputError("must be odd (same-size convolution)", path, name)
    return dict(out_channels=options["out_channels"], up_block_types=up_types,
                conv_out_kernel=options["conv_out_kernel"],
                center_input_sample=bool(options["center_input_sample"]))


@dataclasses.dataclass(frozen=True)
class ControlNetConfig(BackboneConfig):
  """ControlNetModel: the UNet's encoder half plus a conditioning-image embedding."""
  conditioning_channels: int
  conditioning_embedding_out_channels: tuple[int, ...]
  conditioning_channel_order: str
  global_pool_conditions: bool

  OPTION_TABLES: ClassVar = (model_options.CONTROLNET_DEFAULTS, model_options.CONTROLNET_FIXED)
  MID_BLOCK_TYPES: ClassVar = (CROSS_ATTENTION_MID, PLAIN_MID)

  @classmethod
  def own_fields(cls, options: dict[str, Any], path: Path) -> dict[str, Any]:
    for name in ("layers_per_block", "cross_attention_dim"):
      if not isinstance(options[name], int):
        raise InputError("ControlNetModel takes one integer", path, name)
    return dict(conditioning_channels=options["conditioning_channels"],
                conditioning_embedding_out_channels=tuple(
                    options["conditioning_embedding_out_channels"]),
                conditioning_channel_order=options["controlnet_conditioning_channel_order"],
                global_pool_conditions=bool(options["global_pool_conditions"]))


@dataclasses.dataclass(frozen=True)
class AutoencoderConfig:
  """AutoencoderKL. Latents for the diffusion model are (z - shift_factor) * scaling_factor."""
  in_channels: int
  out_channels: int
  block_out_channels: tuple[int, ...]
  layers_per_block: int
  latent_channels: int
  norm_num_groups: int
  scaling_factor: float
  shift_factor: float
  use_quant_conv: bool
  use_post_quant_conv: bool
  mid_block_add_attention: bool

  def to_diffusion_latents(self, z):
    """Posterior samples z -> the latents the UNet sees: (z - shift_factor) * scaling_factor."""
    return (z - self.shift_factor) * self.scaling_factor

  def from_diffusion_latents(self, latents):
    """The inverse of to_diffusion_latents (what the decoder takes)."""
    return latents / self.scaling_factor + self.shift_factor

  @classmethod
  def from_dict(cls, raw: Mapping[str, Any], path: str | os.PathLike = "config.json"
                ) -> "AutoencoderConfig":
    path = Path(path)
    options = model_options.read_options(raw, path, model_options.AUTOENCODER_DEFAULTS,
                                         model_options.AUTOENCODER_FIXED)
    channels = options["block_out_channels"]
    for name, expected in (("down_block_types", "DownEncoderBlock2D"),
                           ("up_block_types", "UpDecoderBlock2D")):
      if len(options[name]) != len(channels) or any(t != expected for t in options[name]):
        raise InputError(f"this port implements {len(channels)} x {expected!r} (one per entry "
                         "of block_out_channels)", path, name)
    groups = options["norm_num_groups"]
    if any(c % groups for c in channels):
      raise InputError(f"must divide every block's channels {list(channels)}", path,
                       "norm_num_groups")
    return cls(in_channels=options["in_channels"], out_channels=options["out_channels"],
               block_out_channels=tuple(channels), layers_per_block=options["layers_per_block"],
               latent_channels=options["latent_channels"], norm_num_groups=groups,
               scaling_factor=float(options["scaling_factor"]),
               shift_factor=float(options["shift_factor"] or 0.0),
               use_quant_conv=bool(options["use_quant_conv"]),
               use_post_quant_conv=bool(options["use_post_quant_conv"]),
               mid_block_add_attention=bool(options["mid_block_add_attention"]))


def component_directory(path: str | os.PathLike, component: str) -> Path:
  """`path` itself if it holds a config.json, else `path`/`component` (a pipeline directory)."""
  path = Path(path)
  for candidate in (path, path / component):
    if (candidate / "config.json").is_file():
      return candidate
  raise InputError(f"no config.json here nor in its '{component}' subdirectory", path)


def read_config(directory: Path) -> dict[str, Any]:
  """A component directory's config.json (an InputError naming it when missing or malformed)."""
  return files.read_json(directory / "config.json")
