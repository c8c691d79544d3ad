"""Reading diffusers/transformers weights from safetensors, and checking them against a model.

Only safetensors are read: pickled checkpoints (.bin, .ckpt, .pt) can run arbitrary code when
loaded, so they are refused with a message saying how to convert them.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from signerf_jax import files
from signerf_jax.errors import InputError

# diffusers components (unet, vae, controlnet) and transformers models (text encoders).
WEIGHT_STEMS = ("diffusion_pytorch_model", "model")
PICKLE_SUFFIXES = (".bin", ".ckpt", ".pt", ".pth")


def find_weight_files(directory: str | os.PathLike, variant: str | None = None) -> list[Path]:
  """The safetensors file(s) of one component directory (single file or sharded with an index).

  Args:
    directory: e.g. `<checkpoint>/unet`.
    variant: diffusers weight variant such as "fp16" (`diffusion_pytorch_model.fp16.safetensors`);
      None prefers the plain file and falls back to any variant present.
  """
  directory = Path(directory)
  if not directory.is_dir():
    raise InputError("component directory not found", directory)
  infixes = [f".{variant}"] if variant else ["", ".fp16", ".bf16", ".fp32"]
  for stem in WEIGHT_STEMS:
    for infix in infixes:
      single = directory / f"{stem}{infix}.safetensors"
      if single.is_file():
        return [single]
      index = directory / f"{stem}{infix}.safetensors.index.json"
      if index.is_file():
        return _shard_files(directory, index)
  pickled = sorted(p.name for p in directory.iterdir() if p.suffix in PICKLE_SUFFIXES)
  if pickled:
    raise InputError(f"only pickled weights found ({', '.join(pickled)}); they are never "
                     "unpickled here: convert them to safetensors first (e.g. diffusers' "
                     "save_pretrained(..., safe_serialization=True))", directory)
  raise InputError("no .safetensors weights found", directory)


def _shard_files(directory: Path, index: Path) -> list[Path]:
  """The shards a `*.safetensors.index.json` names (its `weight_map`: tensor name -> shard file
  name, as diffusers and transformers write it), each once, in sorted order.

  Raises:
    InputError naming the index and the entry: a weight_map that is missing, empty or not an
    object, or a shard that is not a path inside `directory` (`../../x`, an absolute path or a
    symlink leading out would read a file from anywhere on the machine as weights).
  """
  weight_map = files.read_json(index).get("weight_map")
  if not isinstance(weight_map, dict):
    raise InputError("missing or malformed 'weight_map'", index, "weight_map")
  if not weight_map:
    raise InputError("names no shard (an empty weight_map)", index, "weight_map")
  # Links are not followed: a model in a download cache (Hugging Face's) is a folder of links.
  return sorted({files.contained_path(directory, name, index, f"weight_map[{tensor!r}]",
                                      follow_links=False)
                 for tensor, name in weight_map.items()})


def read_safetensors(paths: Sequence[str | os.PathLike] | str | os.PathLike,
                     dtype=np.float32) -> dict[str, np.ndarray]:
  """All tensors of one or more safetensors files: floating-point ones cast to `dtype` (fp16/bf16
  upcast exactly), integer and boolean ones (buffers such as position ids) kept as they are;
  `check_tensors` refuses them where the model needs weights."""
  from safetensors import safe_open  # pylint: disable=g-import-not-at-top

  if isinstance(paths, (str, os.PathLike)):
    paths = [paths]
  tensors: dict[str, np.ndarray] = {}
  for path in paths:
    path = Path(path)
    if not path.is_file():
      raise InputError("weights file not found", path)
    try:
      with safe_open(str(path), framework="numpy") as handle:
        for name in handle.keys():
          if name in tensors:
            raise InputError("tensor appears in more than one shard", path, name)
          tensor = np.asarray(handle.get_tensor(name))
          tensors[name] = tensor if tensor.dtype.kind in "biu" else tensor.astype(dtype)
    except InputError:
      raise
    except Exception as error:  # safetensors raises its own error types on corrupt headers.
      raise InputError(f"not a readable safetensors file ({error})", path) from None
  return tensors


def check_tensors(expected_shapes: Mapping[str, tuple[int, ...]],
                  tensors: Mapping[str, np.ndarray], source: str | os.PathLike,
                  ignore: Iterable[str] = ()) -> None:
  """Raises InputError unless `tensors` has exactly the expected names and shapes, each of
  floating-point values, all finite (NaN weights would only show as NaN images much later).

  Args:
    expected_shapes: reference-framework tensor name -> shape the model needs.
    tensors: what the checkpoint holds.
    source: the checkpoint path, named in the error.
    ignore: checkpoint names that may be present without being used (e.g. position_ids buffers).
  """
  ignore = set(ignore)
  missing = sorted(set(expected_shapes) - set(tensors))
  extra = sorted(set(tensors) - set(expected_shapes) - ignore)
  if missing:
    raise InputError(f"missing tensor {missing[0]} (expected shape "
                     f"{tuple(expected_shapes[missing[0]])}; {len(missing)} missing in all)",
                     source, missing[0])
  if extra:
    raise InputError(f"unexpected tensor {extra[0]} with shape {tuple(tensors[extra[0]].shape)} "
                     f"({len(extra)} unexpected in all): does the config match the weights?",
                     source, extra[0])
  for name, shape in expected_shapes.items():
    tensor = tensors[name]
    if tuple(tensor.shape) != tuple(shape):
      raise InputError(f"tensor {name} has shape {tuple(tensor.shape)} but the config "
                       f"needs {tuple(shape)}", source, name)
    if tensor.dtype.kind in "biuOSU":  # Not "f": ml_dtypes' bfloat16 is kind "V".
      raise InputError(f"tensor {name} holds {tensor.dtype} values; the model needs "
                       "floating-point weights", source, name)
    finite = np.isfinite(tensor)
    if not finite.all():
      raise InputError(f"tensor {name} has {tensor.size - int(finite.sum())} NaN or infinite "
                       "values", source, name)
