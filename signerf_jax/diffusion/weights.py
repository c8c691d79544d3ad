"""diffusers tensor names and layouts <-> Flax parameters, for the UNet, ControlNet and VAE.

The Flax modules are named after diffusers' attributes, with list items as `<list>_<index>`
(`down_blocks.0.attentions.1.proj_in.weight` <-> `down_blocks_0/attentions_1/proj_in/kernel`),
so a parameter's diffusers name follows from its Flax path. Layouts differ only in:
  * convolution kernels: torch OIHW <-> Flax HWIO;
  * dense kernels: torch [out, in] <-> Flax [in, out];
  * norms: torch `weight` <-> Flax `scale`.
The table of expected names and shapes comes from `jax.eval_shape` of the module's `init`
(abstract: no parameter is computed), so loading never runs Flax initialisers; parameters are
built directly from the checkpoint's numpy arrays.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Mapping

import flax.linen as nn
import jax
import numpy as np
from flax import traverse_util

from signerf_jax import safetensors_io

# diffusers attributes that are nn.ModuleLists: their items are named `<attribute>_<index>`.
LIST_ATTRIBUTES = frozenset({
    "down_blocks", "up_blocks", "resnets", "attentions", "transformer_blocks", "downsamplers",
    "upsamplers", "to_out", "net", "blocks", "controlnet_down_blocks"})
FlaxPath = tuple[str, ...]


def reference_name(path: FlaxPath) -> str:
  """The diffusers tensor name of a Flax parameter path."""
  parts = []
  for segment in path[:-1]:
    attribute, _, index = segment.rpartition("_")
    parts.extend([attribute, index] if attribute in LIST_ATTRIBUTES and index.isdigit()
                 else [segment])
  parts.append("bias" if path[-1] == "bias" else "weight")
  return ".".join(parts)


def _reference_axes(path: FlaxPath, ndim: int) -> tuple[int, ...] | None:
  """The Flax axes that diffusers stores first to last, for parameter `path` of `ndim` axes;
  None when the layouts agree. Convolution kernels HWIO -> OIHW, dense [in, out] -> [out, in]."""
  if path[-1] == "kernel" and ndim == 4:
    return (3, 2, 0, 1)
  if path[-1] == "kernel" and ndim == 2:
    return (1, 0)
  return None


def reference_shape(path: FlaxPath, shape: tuple[int, ...]) -> tuple[int, ...]:
  """The shape diffusers stores for the Flax parameter `path` of shape `shape`."""
  axes = _reference_axes(path, len(shape))
  return tuple(shape) if axes is None else tuple(shape[axis] for axis in axes)


def from_reference_layout(path: FlaxPath, tensor: np.ndarray) -> np.ndarray:
  """A diffusers tensor rearranged into the Flax layout of parameter `path`."""
  axes = _reference_axes(path, tensor.ndim)
  return tensor if axes is None else np.ascontiguousarray(tensor.transpose(np.argsort(axes)))


def to_reference_layout(path: FlaxPath, array: np.ndarray) -> np.ndarray:
  """A Flax parameter rearranged into diffusers' layout (the inverse of from_reference_layout)."""
  axes = _reference_axes(path, array.ndim)
  return array if axes is None else np.ascontiguousarray(array.transpose(axes))


def abstract_params(module: nn.Module) -> dict[FlaxPath, jax.ShapeDtypeStruct]:
  """Flat {Flax path: shape} of the module's parameters, without computing any of them.

  The module must provide `example_inputs()` (abstract inputs that reach every parameter).
  """
  variables = jax.eval_shape(lambda inputs: module.init(jax.random.key(0), **inputs),
                             module.example_inputs())
  return traverse_util.flatten_dict(variables["params"])


def expected_shapes(module: nn.Module) -> dict[str, tuple[int, ...]]:
  """{diffusers tensor name: diffusers shape} that a checkpoint for `module` must hold."""
  return {reference_name(path): reference_shape(path, leaf.shape)
          for path, leaf in abstract_params(module).items()}


def params_from_tensors(module: nn.Module, tensors: Mapping[str, np.ndarray],
                        source: str | os.PathLike, dtype=np.float32) -> dict:
  """Flax params for `module` from diffusers-named tensors (e.g. a state dict as numpy).

  Raises:
    InputError naming `source` and the tensor (with both shapes) when a tensor is missing,
    unexpected, or of the wrong shape.
  """
  shapes = abstract_params(module)
  expected = {reference_name(path): reference_shape(path, leaf.shape)
              for path, leaf in shapes.items()}
  safetensors_io.check_tensors(expected, tensors, source)
  flat = {path: jax.device_put(from_reference_layout(path, np.asarray(tensors[reference_name(path)],
                                                                      dtype)))
          for path in shapes}
  return traverse_util.unflatten_dict(flat)


def load_params(module: nn.Module, directory: str | os.PathLike, dtype=np.float32,
                variant: str | None = None,
                rename: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]] | None = None
                ) -> dict:
  """Reads a diffusers component directory's safetensors into Flax params for `module`.

  Args:
    rename: optional rewrite of legacy tensor names before checking (the VAE's old attention).
  """
  paths = safetensors_io.find_weight_files(Path(directory), variant)
  tensors = safetensors_io.read_safetensors(paths, dtype)
  if rename is not None:
    tensors = rename(tensors)
  # Errors name the weights file, or the directory when the weights are sharded over several.
  return params_from_tensors(module, tensors, paths[0] if len(paths) == 1 else directory, dtype)


def random_params(module: nn.Module, seed: int = 0, dtype=np.float32) -> dict:
  """Random parameters of the right shapes, built in numpy (no Flax initialiser runs).

  Kernels ~ N(0, 1/fan_in) so activations keep their scale through depth; norm scales ~ 1 and
  biases ~ 0 with small noise. For benchmarks and loader round trips, not for training.
  """
  rng = np.random.default_rng(seed)
  flat = {}
  for path, leaf in abstract_params(module).items():
    shape = leaf.shape
    noise = rng.standard_normal(shape, dtype=np.float32)
    if path[-1] == "kernel":
      value = noise / np.float32(np.sqrt(np.prod(shape[:-1])))  # fan-in
    elif path[-1] == "scale":
      value = 1 + np.float32(0.1) * noise
    else:
      value = np.float32(0.1) * noise
    flat[path] = jax.device_put(value.astype(dtype))
  return traverse_util.unflatten_dict(flat)
