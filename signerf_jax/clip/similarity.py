"""CLIP text-image directional similarity (StyleGAN-NADA; InstructPix2Pix, Instruct-NeRF2NeRF).

For an original image I_o with caption T_o and its edit I_e with caption T_e,

  sim_dir = cos(E_img(I_e) - E_img(I_o), E_txt(T_e) - E_txt(T_o)),

where E_img / E_txt are CLIP's projected image / text embeddings, each normalised to unit length
before the difference (as StyleGAN-NADA's and InstructPix2Pix's implementations do). It measures
whether the image changed in the direction the captions describe; the paper (Table 1) reports its
mean over views: 0.23 for SIGNeRF's diffusion edits, 0.2125 for its NeRF renders.

The model is a user-provided transformers CLIP checkpoint, loaded without PyTorch:
  * a `CLIPModel` folder (what `CLIPModel.save_pretrained` / the hub's openai/clip-vit-* hold):
    config.json (text_config, vision_config, projection_dim), model.safetensors (text_model.*,
    vision_model.*, text_projection, visual_projection), the tokenizer's vocab.json + merges.txt
    and optionally preprocessor_config.json; or
  * separate folders: a CLIPVisionModelWithProjection, a CLIPTextModelWithProjection and a
    tokenizer folder (the text folder by default).
Images go through `clip.preprocessing` (bit-exact with transformers' PIL backend); the text tower
and the tokenizer are `clip.text` and `clip.tokenizer`.

InstructPix2Pix's own metric script resizes with torch's (non-antialiased) bicubic to a square
instead of CLIP's shortest-side resize and centre crop, so its numbers are close to, not identical
with, these.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax import files
from signerf_jax import safetensors_io
from signerf_jax.clip import preprocessing as clip_preprocessing
from signerf_jax.clip import text as clip_text
from signerf_jax.clip import tokenizer as tokenizer_lib
from signerf_jax.clip import vision as clip_vision
from signerf_jax.errors import InputError

PREPROCESSOR_CONFIG = "preprocessor_config.json"
# CLIPModel tensors that neither tower uses.
UNUSED_TENSORS = ("logit_scale",)
DEFAULT_BATCH_SIZE = 16


@dataclasses.dataclass(frozen=True, eq=False)
class CLIPModel:
  """Both CLIP towers with projection, the tokenizer and the image preprocessing.

  Attributes:
    text_encoder: a CLIPTextModelWithProjection (`text_embeds` in the joint space).
    vision_encoder: a CLIPVisionModelWithProjection (`image_embeds` in the joint space).
    tokenizer: the checkpoint's CLIP BPE tokenizer.
    preprocessing: resize, crop and normalisation of the checkpoint's image processor.
    batch_size: images per forward pass (a fixed shape: the last batch is padded).
  """

  text_encoder: clip_text.TextEncoder
  vision_encoder: clip_vision.VisionEncoder
  tokenizer: tokenizer_lib.Tokenizer
  preprocessing: clip_preprocessing.CLIPPreprocessing
  batch_size: int = DEFAULT_BATCH_SIZE


def _read_preprocessing(directory: Path) -> clip_preprocessing.CLIPPreprocessing:
  path = directory / PREPROCESSOR_CONFIG
  if not path.is_file():
    return clip_preprocessing.CLIPPreprocessing()
  config = files.read_json(path)
  return clip_preprocessing.CLIPPreprocessing.from_dict(config, path)


def _load_joint_checkpoint(directory: Path
                           ) -> tuple[clip_text.TextEncoder, clip_vision.VisionEncoder]:
  """Both towers of a CLIPModel folder (one config.json, one state dict)."""
  config_path = directory / "config.json"
  config = files.read_json(config_path)
  if not isinstance(config, dict) or not isinstance(config.get("vision_config"), dict) or (
      not isinstance(config.get("text_config"), dict)):
    raise InputError("expected a CLIPModel config with text_config and vision_config objects",
                     config_path)
  # CLIPModel projects both towers to the top-level projection_dim.
  projection_dim = config.get("projection_dim", 512)
  text_config = dataclasses.replace(
      clip_text.CLIPTextConfig.from_dict(config["text_config"], config_path, with_projection=True),
      projection_dim=projection_dim)
  vision_config = dataclasses.replace(
      clip_vision.CLIPVisionConfig.from_dict(config["vision_config"], config_path,
                                             with_projection=True),
      projection_dim=projection_dim)
  tensors = safetensors_io.read_safetensors(safetensors_io.find_weight_files(directory))
  vision_names = {name for name in tensors if name.startswith(clip_vision.VISION_MODEL_PREFIX)}
  vision_names.add(clip_vision.PROJECTION_NAME)
  text = {name: value for name, value in tensors.items()
          if name not in vision_names and name not in UNUSED_TENSORS}
  vision = {name: tensors[name] for name in vision_names if name in tensors}
  return (clip_text.TextEncoder(text_config,
                                clip_text.params_from_tensors(text_config, text, directory)),
          clip_vision.VisionEncoder(vision_config,
                                    clip_vision.params_from_tensors(vision_config, vision,
                                                                    directory)))


def load_clip_model(directory: str | os.PathLike | None = None, *,
                    vision_directory: str | os.PathLike | None = None,
                    text_directory: str | os.PathLike | None = None,
                    tokenizer_directory: str | os.PathLike | None = None,
                    batch_size: int = DEFAULT_BATCH_SIZE) -> CLIPModel:
  """A CLIP model from a CLIPModel folder, or from separate tower folders.

  Args:
    directory: a CLIPModel folder (see the module docstring); excludes the next two.
    vision_directory, text_directory: CLIPVisionModelWithProjection and
      CLIPTextModelWithProjection folders, used together instead of `directory`.
    tokenizer_directory: vocab.json + merges.txt; defaults to `directory` / `text_directory`.
    batch_size: images per forward pass.
  """
  separate = (vision_directory, text_directory)
  if (directory is None) == all(path is None for path in separate) or (
      directory is None and None in separate):
    raise ValueError("give either a CLIPModel directory or both vision_directory and "
                     "text_directory")
  if directory is not None:
    directory = Path(directory)
    text_encoder, vision_encoder = _load_joint_checkpoint(directory)
    preprocessing = _read_preprocessing(directory)
    tokenizer_directory = directory if tokenizer_directory is None else tokenizer_directory
  else:
    text_encoder = clip_text.load_text_encoder(text_directory, with_projection=True)
    vision_encoder = clip_vision.load_vision_encoder(vision_directory, with_projection=True)
    if text_encoder.config.projection_dim != vision_encoder.config.projection_dim:
      raise InputError(f"the text tower projects to {text_encoder.config.projection_dim} "
                       f"dimensions, the vision tower to {vision_encoder.config.projection_dim}",
                       vision_directory, "projection_dim")
    preprocessing = _read_preprocessing(Path(vision_directory))
    tokenizer_directory = text_directory if tokenizer_directory is None else tokenizer_directory
  if (preprocessing.crop_height, preprocessing.crop_width) != (
      (vision_encoder.config.image_size,) * 2):
    raise InputError(f"the image processor crops {preprocessing.crop_height}x"
                     f"{preprocessing.crop_width} but the vision tower takes "
                     f"{vision_encoder.config.image_size}x{vision_encoder.config.image_size}",
                     directory or vision_directory, "crop_size")
  tokenizer = tokenizer_lib.CLIPTokenizer.from_directory(tokenizer_directory)
  return CLIPModel(text_encoder, vision_encoder, tokenizer, preprocessing, batch_size)


def image_embeddings(model: CLIPModel, images) -> np.ndarray:
  """[N, projection_dim] float32 `image_embeds` (not normalised) of [N, H, W, 3] images (uint8,
  or float in [0, 1]), in fixed-size batches so that every call reuses one compilation."""
  pixels = model.preprocessing(images)
  batches = []
  for start in range(0, len(pixels), model.batch_size):
    batch = pixels[start:start + model.batch_size]
    padded = np.pad(batch, ((0, model.batch_size - len(batch)),) + ((0, 0),) * 3)
    batches.append(np.asarray(model.vision_encoder(padded).image_embeds)[:len(batch)])
  return np.concatenate(batches)


def text_embeddings(model: CLIPModel, texts: Sequence[str]) -> np.ndarray:
  """[T, projection_dim] float32 `text_embeds` (not normalised) of T captions."""
  return np.asarray(model.text_encoder(model.tokenizer.tokenize(list(texts))).text_embeds)


@jax.jit
def directional_similarity(original_image_embeds, edited_image_embeds, original_text_embeds,
                           edited_text_embeds):
  """[N] cos(e_img(edited) - e_img(original), e_txt(edited) - e_txt(original)), with every
  embedding normalised first; image embeds are [N, P], text embeds [P] or [N, P]."""
  def unit(vector):
    return vector / jnp.linalg.norm(vector, axis=-1, keepdims=True)

  image_direction = unit(edited_image_embeds) - unit(original_image_embeds)
  text_direction = unit(edited_text_embeds) - unit(original_text_embeds)
  # torch.nn.functional.cosine_similarity's guard against zero-length directions.
  norms = (jnp.maximum(jnp.linalg.norm(image_direction, axis=-1), 1e-8)
           * jnp.maximum(jnp.linalg.norm(text_direction, axis=-1), 1e-8))
  return jnp.sum(image_direction * text_direction, axis=-1) / norms


def clip_directional_similarity(model: CLIPModel, original_images, edited_images,
                                original_caption: str, edited_caption: str) -> np.ndarray:
  """Per-view CLIP directional similarity of an edit; the paper reports the mean.

  Args:
    model: `load_clip_model(...)`.
    original_images, edited_images: [N, H, W, 3] uint8 or float in [0, 1], view by view (e.g.
      renders of the original and the edited NeRF from the same cameras).
    original_caption, edited_caption: describe the scene before and after the edit.
  Returns:
    [N] float32 in [-1, 1].
  """
  if np.shape(original_images) != np.shape(edited_images):
    raise ValueError(f"original images {np.shape(original_images)} and edited images "
                     f"{np.shape(edited_images)} differ in shape")
  original_text, edited_text = text_embeddings(model, [original_caption, edited_caption])
  return np.asarray(directional_similarity(
      image_embeddings(model, original_images), image_embeddings(model, edited_images),
      original_text, edited_text))
