"""What a diffusers model's config.json may say, and reading it against that.

For UNet2DConditionModel, ControlNetModel and AutoencoderKL: every option diffusers' class takes,
with diffusers' default (`*_DEFAULTS`), and the values this port implements for the options it
restricts (`*_FIXED`; `ANY` marks options that do not change inference). `read_options` overlays
a config.json on the defaults and raises `InputError`, naming the file and the field, on an
unknown option or a value this port does not implement; keys beginning with "_" (diffusers'
metadata) are ignored. `per_block` reads an option given once or per down block.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

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
UNET_DEFAULTS = {
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
UNET_FIXED = {
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
CONTROLNET_DEFAULTS = {
    **_BACKBONE_DEFAULTS,
    "conditioning_channels": 3,
    "controlnet_conditioning_channel_order": "rgb",
    "conditioning_embedding_out_channels": (16, 32, 96, 256),
    "global_pool_conditions": False,
}
CONTROLNET_FIXED = {
    **_BACKBONE_FIXED,
    "controlnet_conditioning_channel_order": ("rgb", "bgr"),
}
AUTOENCODER_DEFAULTS = {
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
AUTOENCODER_FIXED = {
    "act_fn": ("silu", "swish"),
    "sample_size": ANY,
    "force_upcast": ANY,  # a float16 matter; this port computes norms in float32 anyway
    "latents_mean": (None,),
    "latents_std": (None,),
}


def read_options(raw: Mapping[str, Any], path: Path, defaults: Mapping[str, Any],
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


def per_block(options: dict[str, Any], name: str, count: int, path: Path) -> tuple[int, ...]:
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
