"""The configurations of the UNet, ControlNet and AutoencoderKL, parsed from diffusers' config.json.

Each parser takes the JSON dict as diffusers writes it (`save_pretrained`), checks every option
against what this port implements, and returns a frozen dataclass with per-block values spelled
out (tuples, one entry per down block). Unknown options, and options set to a value this port
does not implement, raise `InputError` naming the config file and the field; keys beginning with
"_" (diffusers' metadata) are ignored.

diffusers' historical naming is kept exactly: a UNet's `attention_head_dim` is the *number of
heads* unless `num_attention_heads` is set, and each transformer's head size is then
`block channels // heads` (SD 1.x: 8 heads everywhere; SD 2.x: [5, 10, 20, 20] heads of 64).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, Mapping

from signerf_jax import files
from signerf_jax.errors import InputError

CROSS_ATTENTION_DOWN = "CrossAttnDownBlock2D"
PLAIN_DOWN = "DownBlock2D"
CROSS_ATTENTION_UP = "CrossAttnUpBlock2D"
PLAIN_UP = "UpBlock2D"
CROSS_ATTENTION_MID = "UNetMidBlock2DCrossAttn"
PLAIN_MID = "UNetMidBlock2D"
ANY = object()  # marks options that do not change inference (dropout, sample_size, ...)

# Options shared by the UNet and the ControlNet, with diffusers' defaults.
_BACKBONE_DEFAULTS = {
    "in_channels": 4,
    "flip_sin_to_cos": True,
    "freq_shift": 0,
    "down_block_types": (CROSS_ATTENTION_DOWN,) * 3 + (PLAIN_DOWN,),
    "mid_block_type": CROSS_ATTENTION_MID,
    "only_cross_attention": False,
    "block_out_channels": (320, 640, 1280, 1280),
    "layers_per_block": 2,
    "downsample_padding": 1,
    "mid_block_scale_factor": 1.0,
    "act_fn": "silu",
    "norm_num_groups": 32,
    "norm_eps": 1e-5,
    "cross_attention_dim": 1280,
    "transformer_layers_per_block": 1,
    "encoder_hid_dim": None,
    "encoder_hid_dim_type": None,
    "attention_head_dim": 8,
    "num_attention_heads": None,
    "use_linear_projection": False,
    "class_embed_type": None,
    "addition_embed_type": None,
    "addition_time_embed_dim": None,
    "num_class_embeds": None,
    "upcast_attention": False,
    "resnet_time_scale_shift": "default",
    "projection_class_embeddings_input_dim": None,
    "addition_embed_type_num_heads": 64,
}
_BACKBONE_FIXED = {
    "only_cross_attention": (False,),
    "act_fn": ("silu", "swish"),
    "encoder_hid_dim": (None,),
    "encoder_hid_dim_type": (None,),
    "class_embed_type": (None,),
    "num_class_embeds": (None,),
    "resnet_time_scale_shift": ("default",),
    "addition_embed_type": (None, "text_time"),
    "addition_embed_type_num_heads": ANY,  # used only by addition_embed_type "text"
}
_UNET_DEFAULTS = {
    **_BACKBONE_DEFAULTS,
    "sample_size": None,
    "out_channels": 4,
    "center_input_sample": False,
    "up_block_types": (PLAIN_UP,) + (CROSS_ATTENTION_UP,) * 3,
    "dropout": 0.0,
    "reverse_transformer_layers_per_block": None,
    "dual_cross_attention": False,
    "resnet_skip_time_act": False,
    "resnet_out_scale_factor": 1.0,
    "time_embedding_type": "positional",
    "time_embedding_dim": None,
    "time_embedding_act_fn": None,
    "timestep_post_act": None,
    "time_cond_proj_dim": None,
    "conv_in_kernel": 3,
    "conv_out_kernel": 3,
    "attention_type": "default",
    "class_embeddings_concat": False,
    "mid_block_only_cross_attention": None,
    "cross_attention_norm": None,
}
_UNET_FIXED = {
    **_BACKBONE_FIXED,
    "sample_size": ANY,
    "dropout": ANY,
    # diffusers' UNet2DConditionModel itself refuses num_attention_heads (its issue #2011).
    "num_attention_heads": (None,),
    "reverse_transformer_layers_per_block": (None,),
    "dual_cross_attention": (False,),
    "resnet_skip_time_act": (False,),
    "resnet_out_scale_factor": (1, 1.0),
    "time_embedding_type": ("positional",),
    "time_embedding_act_fn": (None,),
    "timestep_post_act": (None,),
    "time_cond_proj_dim": (None,),
    "attention_type": ("default",),
    "class_embeddings_concat": (False,),
    "mid_block_only_cross_attention": (None, False),
    "cross_attention_norm": (None,),
}
_CONTROLNET_DEFAULTS = {
    **_BACKBONE_DEFAULTS,
    "conditioning_channels": 3,
    "controlnet_conditioning_channel_order": "rgb",
    "conditioning_embedding_out_channels": (16, 32, 96, 256),
    "global_pool_conditions": False,
}
_CONTROLNET_FIXED = {
    **_BACKBONE_FIXED,
    "controlnet_conditioning_channel_order": ("rgb", "bgr"),
}
_AUTOENCODER_DEFAULTS = {
    "in_channels": 3,
    "out_channels": 3,
    "down_block_types": ("DownEncoderBlock2D",),
    "up_block_types": ("UpDecoderBlock2D",),
    "block_out_channels": (64,),
    "layers_per_block": 1,
    "act_fn": "silu",
    "latent_channels": 4,
    "norm_num_groups": 32,
    "sample_size": 32,
    "scaling_factor": 0.18215,
    "shift_factor": None,
    "latents_mean": None,
    "latents_std": None,
    "force_upcast": True,
    "use_quant_conv": True,
    "use_post_quant_conv": True,
    "mid_block_add_attention": True,
}
_AUTOENCODER_FIXED = {
    "act_fn": ("silu", "swish"),
    "sample_size": ANY,
    "force_upcast": ANY,  # a float16 matter; this port computes norms in float32 anyway
    "latents_mean": (None,),
    "latents_std": (None,),
}


def _check_options(raw: Mapping[str, Any], path: Path, defaults: Mapping[str, Any],
                   fixed: Mapping[str, Any]) -> dict[str, Any]:
  """diffusers defaults overlaid with `raw`; raises on unknown or unsupported options."""
  if not isinstance(raw, Mapping):
    raise InputError("a model config must be a JSON object", path)
  options = dict(defaults)
  for name, value in raw.items():
    if name.startswith("_"):
      continue
    if name not in defaults:
      raise InputError(f"unknown option {name!r} (this port does not implement it)", path, name)
    options[name] = tuple(value) if isinstance(value, list) else value
  for name, allowed in fixed.items():
    if allowed is not ANY and options[name] not in allowed:
      raise InputError(f"unsupported value {options[name]!r}; this port implements "
                       f"{' or '.join(repr(a) for a in allowed)}", path, name)
  return options


def _per_block(options: dict[str, Any], name: str, count: int, path: Path) -> tuple[int, ...]:
  """Option `name`: an int broadcast over `count` blocks, or a list of exactly `count` ints."""
  value = options[name]
  if isinstance(value, tuple):
    if len(value) != count or not all(isinstance(v, int) for v in value):
      raise InputError(f"expected {count} integers (one per down block), got {list(value)}",
                       path, name)
    return value
  if not isinstance(value, int):
    raise InputError(f"expected an integer or a list of integers, got {value!r}", path, name)
  return (value,) * count


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


def _backbone_fields(options: dict[str, Any], path: Path, mid_block_types: tuple) -> dict:
  channels = options["block_out_channels"]
  down_types = options["down_block_types"]
  count = len(down_types)
  if not isinstance(channels, tuple) or len(channels) != count:
    raise InputError(f"needs one entry per down block ({count})", path, "block_out_channels")
  for block_type in down_types:
    if block_type not in (CROSS_ATTENTION_DOWN, PLAIN_DOWN):
      raise InputError(f"unsupported block type {block_type!r}; this port implements "
                       f"{CROSS_ATTENTION_DOWN} and {PLAIN_DOWN}", path, "down_block_types")
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
  heads_field = "attention_head_dim" if options["num_attention_heads"] is None else \
      "num_attention_heads"
  heads = _per_block(options, heads_field, count, path)
  for block_channels, block_heads in zip(channels, heads):
    if block_channels % block_heads:
      raise InputError(f"{block_heads} heads do not divide {block_channels} channels", path,
                       heads_field)
  cross_attention_dims = _per_block(options, "cross_attention_dim", count, path)
  if len(set(cross_attention_dims)) != 1:
    raise InputError("a different cross-attention width per block is not implemented", path,
                     "cross_attention_dim")
  if options["addition_embed_type"] == "text_time":
    for name in ("addition_time_embed_dim", "projection_class_embeddings_input_dim"):
      if not isinstance(options[name], int):
        raise InputError("required (an integer) when addition_embed_type is 'text_time'", path,
                         name)
  return dict(
      in_channels=options["in_channels"],
      block_out_channels=channels,
      down_block_types=down_types,
      layers_per_block=_per_block(options, "layers_per_block", count, path),
      transformer_layers_per_block=_per_block(options, "transformer_layers_per_block", count, path),
      num_attention_heads=heads,
      cross_attention_dim=cross_attention_dims[0],
      mid_block_type=options["mid_block_type"],
      mid_block_scale_factor=float(options["mid_block_scale_factor"]),
      downsample_padding=options["downsample_padding"],
      norm_num_groups=groups,
      norm_eps=float(options["norm_eps"]),
      use_linear_projection=bool(options["use_linear_projection"]),
      upcast_attention=bool(options["upcast_attention"]),
      flip_sin_to_cos=bool(options["flip_sin_to_cos"]),
      freq_shift=float(options["freq_shift"]),
      time_embedding_dim=options.get("time_embedding_dim") or channels[0] * 4,
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

  @classmethod
  def from_dict(cls, raw: Mapping[str, Any], path: str | os.PathLike = "config.json"
                ) -> "UNetConfig":
    path = Path(path)
    options = _check_options(raw, path, _UNET_DEFAULTS, _UNET_FIXED)
    fields = _backbone_fields(options, path, (CROSS_ATTENTION_MID, PLAIN_MID, None))
    up_types = options["up_block_types"]
    if len(up_types) != len(fields["down_block_types"]):
      raise InputError("needs as many entries as down_block_types", path, "up_block_types")
    for block_type in up_types:
      if block_type not in (CROSS_ATTENTION_UP, PLAIN_UP):
        raise InputError(f"unsupported block type {block_type!r}; this port implements "
                         f"{CROSS_ATTENTION_UP} and {PLAIN_UP}", path, "up_block_types")
    for name in ("conv_in_kernel", "conv_out_kernel"):
      if options[name] % 2 != 1:
        raise InputError("must be odd (same-size convolution)", path, name)
    return cls(**fields, out_channels=options["out_channels"], up_block_types=up_types,
               conv_out_kernel=options["conv_out_kernel"],
               center_input_sample=bool(options["center_input_sample"]))


@dataclasses.dataclass(frozen=True)
class ControlNetConfig(BackboneConfig):
  """ControlNetModel: the UNet's encoder half plus a conditioning-image embedding."""
  conditioning_channels: int
  conditioning_embedding_out_channels: tuple[int, ...]
  conditioning_channel_order: str
  global_pool_conditions: bool

  @classmethod
  def from_dict(cls, raw: Mapping[str, Any], path: str | os.PathLike = "config.json"
                ) -> "ControlNetConfig":
    path = Path(path)
    options = _check_options(raw, path, _CONTROLNET_DEFAULTS, _CONTROLNET_FIXED)
    if not isinstance(options["layers_per_block"], int):
      raise InputError("ControlNetModel takes one integer", path, "layers_per_block")
    if not isinstance(options["cross_attention_dim"], int):
      raise InputError("ControlNetModel takes one integer", path, "cross_attention_dim")
    fields = _backbone_fields(options, path, (CROSS_ATTENTION_MID, PLAIN_MID))
    return cls(**fields, conditioning_channels=options["conditioning_channels"],
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
    options = _check_options(raw, path, _AUTOENCODER_DEFAULTS, _AUTOENCODER_FIXED)
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
  return files.read_json(directory / "config.json")
