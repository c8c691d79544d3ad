"""The components of a diffusers pipeline: where they are and loading each of them.

A pipeline directory names its components in `model_index.json` (`name: [library, class]`, one
subfolder each: unet, controlnet, vae, text_encoder(_2), tokenizer(_2), scheduler); without an
index its subfolders are taken as they are. Any component may instead be given as a directory of
its own (e.g. a ControlNet stored apart from its base model); `find_components` resolves both
into a `Components`, which names what is missing and where it was looked for.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

from signerf_jax import files
from signerf_jax.clip import text as clip_text
from signerf_jax.clip.tokenizer import Tokenizer, load_tokenizer
from signerf_jax.diffusion import sampler
from signerf_jax.diffusion.controlnet import load_controlnet
from signerf_jax.diffusion.unet import load_unet
from signerf_jax.diffusion.vae import load_vae
from signerf_jax.errors import InputError

MODEL_INDEX = "model_index.json"
COMPONENTS = ("unet", "controlnet", "vae", "text_encoder", "text_encoder_2", "tokenizer",
              "tokenizer_2", "scheduler")


def _read_model_index(path: Path) -> tuple[dict[str, Path], dict[str, Any]]:
  """(subdirectories of the components `model_index.json` names, the pipeline's options).

  Entries are `name: [library, class]`, with [null, null] for an absent component (e.g. a
  safety checker saved as None); other entries are options (force_zeros_for_empty_prompt, ...).
  """
  index_path = path / MODEL_INDEX
  index = files.read_json(index_path)
  components, options = {}, {}
  for name, value in index.items():
    if name.startswith("_"):
      continue
    if not isinstance(value, list):
      options[name] = value
    elif len(value) != 2:
      raise InputError(f"expected [library, class], got {value!r}", index_path, name)
    elif value[1] is not None and name in COMPONENTS:
      # Only the fixed COMPONENTS names become folders: an entry's key is never used as a path
      # (a key such as "../../elsewhere" would otherwise name a folder outside the pipeline),
      # and the components this project does not use (safety_checker, ...) are not read.
      components[name] = path / name
  return components, options


@dataclasses.dataclass(frozen=True)
class Components:
  """Where a pipeline's components are.

  Attributes:
    directories: component name -> its directory, for the components found.
    options: the pipeline's options in model_index.json (force_zeros_for_empty_prompt, ...).
    path: the pipeline directory; None when every component is given apart.
    searched: where the components not found were looked for, for error messages.
  """
  directories: dict[str, Path]
  options: dict[str, Any]
  path: Path | None
  searched: str

  def require(self, name: str) -> Path:
    """The directory of component `name`; raises InputError saying where it was looked for."""
    if name not in self.directories:
      raise InputError(f"missing pipeline component {name!r}: {self.searched}; pass "
                       f"{name}=<directory>", self.path, name)
    return self.directories[name]


def find_components(path: Path | None, overrides: Mapping[str, Any]) -> Components:
  """Where each component is: an explicit path, else the pipeline directory's subfolder.

  Args:
    path: the pipeline directory, or None.
    overrides: component name -> its directory given apart, or None.
  """
  pipeline_components, options = {}, {}
  if path is None:
    searched = "no pipeline directory was given"
  elif not path.is_dir():
    raise InputError("pipeline directory not found", path)
  elif (path / MODEL_INDEX).is_file():
    pipeline_components, options = _read_model_index(path)
    searched = f"{MODEL_INDEX} does not list it"
  else:  # No index: a folder of component subdirectories.
    pipeline_components = {name: path / name for name in COMPONENTS if (path / name).is_dir()}
    searched = f"no such subdirectory (and no {MODEL_INDEX})"
  directories = {}
  for name in COMPONENTS:
    directory = (Path(overrides[name]) if overrides.get(name) is not None
                 else pipeline_components.get(name))
    if directory is not None:
      if not directory.is_dir():
        raise InputError(f"component {name!r} not found", directory, name)
      directories[name] = directory
  return Components(directories, options, path, searched)


def load_networks(components: Components, dtype, **network_options) -> sampler.DiffusionModels:
  """The UNet, the VAE and, when the pipeline has one, the ControlNet, with their parameters
  (`network_options`: variant, attention and compute_dtype of their loaders)."""
  unet_module, unet_params = load_unet(components.require("unet"), dtype, **network_options)
  vae_module, vae_params = load_vae(components.require("vae"), dtype, **network_options)
  controlnet_module, controlnet_params = None, None
  if "controlnet" in components.directories:
    controlnet_module, controlnet_params = load_controlnet(components.directories["controlnet"],
                                                           dtype, **network_options)
  return sampler.DiffusionModels(unet_params, vae_params, controlnet_params, unet_module,
                                 vae_module, controlnet_module)


def load_text_encoders(components: Components, sdxl: bool
                       ) -> tuple[tuple[Tokenizer, ...], tuple[clip_text.TextEncoder, ...]]:
  """The tokenizers and text encoders: SD's pair; SDXL's second pair, after the first when the
  pipeline has it."""
  if sdxl:
    encoder_names = [("tokenizer_2", "text_encoder_2")]
    if "text_encoder" in components.directories or "tokenizer" in components.directories:
      encoder_names.insert(0, ("tokenizer", "text_encoder"))
  else:
    encoder_names = [("tokenizer", "text_encoder")]
  tokenizers = tuple(load_tokenizer(components.require(name)) for name, _ in encoder_names)
  text_encoders = tuple(clip_text.load_text_encoder(components.require(name))
                        for _, name in encoder_names)
  return tokenizers, text_encoders
