"""Writing the default model as a diffusers-layout checkpoint, and loading it back.

    export.write_checkpoint(directory, architecture, params, tokenizer)

writes
  model_index.json                  StableDiffusionControlNetInpaintPipeline and its parts;
  vae/, unet/, controlnet/          config.json + diffusion_pytorch_model.safetensors;
  text_encoder/                     config.json + model.safetensors (transformers >= 5 names);
  tokenizer/                        the word tokenizer (`word_tokenizer.WordTokenizer.save`);
  scheduler/scheduler_config.json   the training noise schedule.
Tensors get diffusers' / transformers' names and torch layouts (`weights.reference_name`,
`weights.to_reference_layout`, `clip_text.tensors_from_params`), stored in `dtype` (float16 by
default: half the size, and the loaders convert exactly back to float32). Each file is written
atomically in place; nothing else in the directory (a model card, the user's notes) is touched.

`load_checkpoint` reads it back through the same component loaders any diffusers checkpoint goes
through (`load_vae`, `load_unet`, `load_controlnet`, `load_text_encoder`, `load_tokenizer`,
`load_scheduler_config`).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import jax
import numpy as np
import safetensors.numpy
from flax import traverse_util

from signerf_jax import files
from signerf_jax.clip import text as clip_text
from signerf_jax.clip import tokenizer as tokenizer_lib
from signerf_jax.clip import word_tokenizer
from signerf_jax.default_model import model as model_lib
from signerf_jax.diffusion import controlnet as controlnet_lib
from signerf_jax.diffusion import schedulers
from signerf_jax.diffusion import unet as unet_lib
from signerf_jax.diffusion import vae as vae_lib
from signerf_jax.diffusion import weights
from signerf_jax.editing import generation

DIFFUSERS_WEIGHTS = "diffusion_pytorch_model.safetensors"
TRANSFORMERS_WEIGHTS = "model.safetensors"
PIPELINE_CLASS = "StableDiffusionControlNetInpaintPipeline"
COMPONENTS = ("vae", "unet", "text_encoder", "controlnet")  # The trained parameter sets.
# Edits with this model grow the proxy's mask by 8 px at 512 (1 px in a 64 px tile): with the
# 24 other models get it repaints the ring blurred and the edited NeRF keeps it as a halo (on a
# real scene: docs/results.md; the demo's gin_configs/demo.gin).
MASK_DILATION_RADIUS = 8.0


def model_index(architecture: model_lib.Architecture) -> dict[str, Any]:
  """diffusers' model_index.json of the pipeline."""
  return {"_class_name": PIPELINE_CLASS, "_diffusers_version": model_lib.DIFFUSERS_VERSION,
          "vae": ["diffusers", "AutoencoderKL"], "text_encoder": ["transformers", "CLIPTextModel"],
          "tokenizer": ["signerf_jax", word_tokenizer.TOKENIZER_CLASS],
          "unet": ["diffusers", "UNet2DConditionModel"],
          "controlnet": ["diffusers", "ControlNetModel"],
          "scheduler": ["diffusers", architecture.scheduler_class],
          "safety_checker": [None, None], "feature_extractor": [None, None],
          "image_encoder": [None, None], "requires_safety_checker": False,
          generation.MASK_DILATION_KEY: MASK_DILATION_RADIUS}


def diffusers_tensors(params, dtype=np.float16) -> dict[str, np.ndarray]:
  """Flax parameters of a UNet, ControlNet or VAE -> diffusers-named torch-layout tensors."""
  return {weights.reference_name(path): np.ascontiguousarray(
      weights.to_reference_layout(path, np.asarray(leaf)).astype(dtype))
          for path, leaf in traverse_util.flatten_dict(params).items()}


def _write_safetensors(path: Path, tensors: dict[str, np.ndarray]) -> None:
  with files.atomic_path(path) as temporary:
    safetensors.numpy.save_file(tensors, str(temporary))


def write_checkpoint(directory: str | os.PathLike, architecture: model_lib.Architecture,
                     params: dict[str, Any], tokenizer: word_tokenizer.WordTokenizer,
                     dtype=np.float16) -> dict[str, int]:
  """Writes the checkpoint (module docstring) into `directory`.

  Args:
    params: {"vae", "unet", "controlnet", "text_encoder"} Flax parameters.
  Returns:
    {component: bytes on disk} for every component folder and "total".
  """
  directory = Path(directory)
  files.write_json(directory / "model_index.json", model_index(architecture))
  for name, config in (("vae", architecture.vae_config()), ("unet", architecture.unet_config()),
                       ("controlnet", architecture.controlnet_config())):
    files.write_json(directory / name / "config.json", config)
    _write_safetensors(directory / name / DIFFUSERS_WEIGHTS, diffusers_tensors(params[name], dtype))
  text_config = architecture.text_encoder_config(tokenizer.vocab_size)
  files.write_json(directory / "text_encoder" / "config.json", text_config)
  text_tensors = clip_text.tensors_from_params(
      clip_text.CLIPTextConfig.from_dict(text_config), params["text_encoder"])
  _write_safetensors(directory / "text_encoder" / TRANSFORMERS_WEIGHTS,
                     {name: tensor.astype(dtype) for name, tensor in text_tensors.items()})
  tokenizer.save(directory / "tokenizer")
  files.write_json(directory / "scheduler" / "scheduler_config.json",
                   architecture.scheduler_config())
  sizes = {folder.name: sum(path.stat().st_size for path in folder.rglob("*") if path.is_file())
           for folder in sorted(directory.iterdir()) if folder.is_dir()}
  sizes["total"] = sum(path.stat().st_size for path in directory.rglob("*") if path.is_file())
  return sizes


@dataclasses.dataclass(frozen=True)
class LoadedCheckpoint:
  """A checkpoint read back through the component loaders."""

  vae: vae_lib.AutoencoderKL
  vae_params: Any
  unet: unet_lib.UNet2DCondition
  unet_params: Any
  controlnet: controlnet_lib.ControlNet
  controlnet_params: Any
  text_encoder: clip_text.TextEncoder
  tokenizer: tokenizer_lib.Tokenizer
  scheduler: schedulers.SchedulerConfig


def load_checkpoint(directory: str | os.PathLike) -> LoadedCheckpoint:
  """Every component of a checkpoint directory, loaded as real checkpoints are."""
  directory = Path(directory)
  vae, vae_params = vae_lib.load_vae(directory)
  unet, unet_params = unet_lib.load_unet(directory)
  controlnet, controlnet_params = controlnet_lib.load_controlnet(directory)
  return LoadedCheckpoint(
      vae=vae, vae_params=vae_params, unet=unet, unet_params=unet_params, controlnet=controlnet,
      controlnet_params=controlnet_params,
      text_encoder=clip_text.load_text_encoder(directory / "text_encoder"),
      tokenizer=tokenizer_lib.load_tokenizer(directory / "tokenizer"),
      scheduler=schedulers.load_scheduler_config(directory / "scheduler"))


def initial_params(directory: str | os.PathLike) -> dict[str, Any]:
  """{COMPONENTS}: an exported model's parameters in float32, to continue training from
  (`stages.train(..., initial=...)`)."""
  loaded = load_checkpoint(directory)
  params = {"vae": loaded.vae_params, "unet": loaded.unet_params,
            "text_encoder": loaded.text_encoder.params, "controlnet": loaded.controlnet_params}
  return jax.tree.map(lambda leaf: np.asarray(leaf, np.float32), params)
