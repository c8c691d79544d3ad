"""Weights named by a sharded checkpoint's index are read only from inside their component folder,
through the whole pipeline loader: a shard the index places elsewhere is an InputError naming
the index and the entry, shards inside (split as diffusers splits them) load as one file."""

from __future__ import annotations

import json
import shutil

import jax
import numpy as np
import pytest
from safetensors.numpy import load_file, save_file

from signerf_jax.diffusion import pipeline, vae
from signerf_jax.editing.config import DEFAULT_MODEL_DIR
from signerf_jax.errors import InputError

WEIGHTS = "diffusion_pytorch_model.safetensors"
INDEX = "diffusion_pytorch_model.safetensors.index.json"


def shard_the_vae(tmp_path, shard_names):
  """A copy of the default model whose VAE weights are split over shards, the i-th tensor (in
  sorted order) into `shard_names[i % len(shard_names)]` (relative to the vae folder), and an
  index naming them; returns (model, index, {tensor: shard name})."""
  model = tmp_path / "model"
  shutil.copytree(DEFAULT_MODEL_DIR, model)
  tensors = load_file(model / "vae" / WEIGHTS)
  (model / "vae" / WEIGHTS).unlink()
  weight_map = {name: shard_names[index % len(shard_names)]
                for index, name in enumerate(sorted(tensors))}
  for shard in set(shard_names):
    path = model / "vae" / shard
    path.parent.mkdir(parents=True, exist_ok=True)
    save_file({name: tensors[name] for name in tensors if weight_map[name] == shard}, path)
  (model / "vae" / INDEX).write_text(json.dumps({"metadata": {}, "weight_map": weight_map}))
  return model, model / "vae" / INDEX, weight_map


def test_a_shard_outside_the_component_folder_names_the_index_and_the_entry(tmp_path):
  # The second shard lies beside the model, not in it: read, it would load whatever is there.
  model, index, weight_map = shard_the_vae(
      tmp_path, ["part-1.safetensors", "../../part-2.safetensors"])
  assert (tmp_path / "part-2.safetensors").is_file()
  with pytest.raises(InputError, match="points outside") as error:
    pipeline.load_pipeline(model)
  first_outside = next(name for name, shard in weight_map.items() if shard.startswith(".."))
  assert error.value.path == str(index) and error.value.field == f"weight_map[{first_outside!r}]"


def test_shards_inside_the_component_folder_load_like_the_single_file(tmp_path):
  model, _, _ = shard_the_vae(tmp_path, ["part-1.safetensors", "shards/part-2.safetensors"])
  _, sharded = vae.load_vae(model / "vae")
  _, single = vae.load_vae(DEFAULT_MODEL_DIR / "vae")
  jax.tree.map(np.testing.assert_array_equal, sharded, single)
