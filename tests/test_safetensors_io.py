import json

import ml_dtypes
import numpy as np
import pytest
from safetensors.numpy import save_file

from signerf_jax import safetensors_io
from signerf_jax.errors import InputError


def test_reads_half_precision_and_sharded_weights(tmp_path):
  component = tmp_path / "unet"
  component.mkdir()
  save_file({"a": np.full((2, 3), 1.5, ml_dtypes.bfloat16)}, component / "part-1.safetensors")
  save_file({"b": np.full(3, 0.25, np.float16)}, component / "part-2.safetensors")
  (component / "diffusion_pytorch_model.safetensors.index.json").write_text(
      '{"weight_map": {"a": "part-1.safetensors", "b": "part-2.safetensors"}}')
  tensors = safetensors_io.read_safetensors(safetensors_io.find_weight_files(component))
  assert tensors["a"].dtype == np.float32 and tensors["a"][0, 0] == 1.5
  assert tensors["b"][0] == 0.25
  safetensors_io.check_tensors({"a": (2, 3), "b": (3,)}, tensors, component)


def test_pickled_weights_are_refused(tmp_path):
  (tmp_path / "diffusion_pytorch_model.bin").write_bytes(b"pickle")
  with pytest.raises(InputError, match="never unpickled"):
    safetensors_io.find_weight_files(tmp_path)


@pytest.mark.parametrize("tensors, message", [
    ({"a": np.zeros((2, 3))}, "missing tensor b"),
    ({"a": np.zeros((2, 3)), "b": np.zeros(3), "c": np.zeros(1)}, "unexpected tensor c"),
    ({"a": np.zeros((3, 2)), "b": np.zeros(3)}, r"a has shape \(3, 2\) but the config needs \(2, 3\)"),
])
def test_mismatches_name_the_tensor_and_shapes(tensors, message):
  with pytest.raises(InputError, match=message) as error:
    safetensors_io.check_tensors({"a": (2, 3), "b": (3,)}, tensors, "ckpt/unet")
  assert error.value.path == "ckpt/unet"


@pytest.mark.parametrize("bad, message", [
    (np.array([0.0, np.nan, 1.0], np.float16), "b has 1 NaN or infinite values"),
    (np.array([0.0, np.inf, -np.inf], np.float32), "b has 2 NaN or infinite values"),
    (np.array([1, 2, 3], np.int64), "b holds int64 values; the model needs floating-point"),
], ids=["nan", "inf", "integer"])
def test_weights_that_are_not_finite_floats_are_refused_naming_tensor_and_file(tmp_path, bad,
                                                                                message):
  path = tmp_path / "model.safetensors"
  save_file({"a": np.zeros((2, 3), np.float32), "b": bad,
             "position_ids": np.arange(3, dtype=np.int64)}, path)
  tensors = safetensors_io.read_safetensors(path)
  assert tensors["position_ids"].dtype == np.int64  # Buffers keep their integer type.
  with pytest.raises(InputError, match=message) as error:
    safetensors_io.check_tensors({"a": (2, 3), "b": (3,)}, tensors, path,
                                 ignore=("position_ids",))
  assert error.value.path == str(path) and error.value.field == "b"


def sharded_component(tmp_path, weight_map):
  """`tmp_path/model/unet` with one shard inside it, a real safetensors file outside the model
  (`tmp_path/outside.safetensors`, which must never be read), and an index of `weight_map`."""
  component = tmp_path / "model" / "unet"
  component.mkdir(parents=True)
  save_file({"a": np.ones(2, np.float32)}, component / "part-1.safetensors")
  save_file({"b": np.ones(3, np.float32)}, tmp_path / "outside.safetensors")
  index = component / "diffusion_pytorch_model.safetensors.index.json"
  index.write_text(json.dumps({"metadata": {}, "weight_map": weight_map}))
  return component, index


@pytest.mark.parametrize("shard", ["../../outside.safetensors", "ABSOLUTE",
                                   "sub/../../outside.safetensors"],
                         ids=["parent", "absolute", "parent_inside"])
def test_an_index_entry_leading_outside_the_component_names_the_index_and_the_entry(tmp_path,
                                                                                    shard):
  if shard == "ABSOLUTE":
    shard = str(tmp_path / "outside.safetensors")
  component, index = sharded_component(tmp_path, {"a": "part-1.safetensors", "b": shard})
  with pytest.raises(InputError, match="points outside") as error:
    safetensors_io.find_weight_files(component)
  assert error.value.path == str(index) and error.value.field == "weight_map['b']"


def test_a_shard_that_is_a_link_into_a_download_cache_is_read(tmp_path):
  # Hugging Face's cache: each file of a model snapshot links to ../../blobs/<hash>.
  component, _ = sharded_component(tmp_path, {"a": "part-1.safetensors",
                                              "b": "link.safetensors"})
  (component / "link.safetensors").symlink_to(tmp_path / "outside.safetensors")
  assert component / "link.safetensors" in safetensors_io.find_weight_files(component)


@pytest.mark.parametrize("weight_map, field, message", [
    ({"a": "part-1.safetensors", "b": 7}, "weight_map['b']", "expected a path"),
    ({"a": "part-1.safetensors", "b": ""}, "weight_map['b']", "empty path"),
    ({}, "weight_map", "names no shard"),
    (["part-1.safetensors"], "weight_map", "malformed"),
])
def test_a_malformed_index_entry_names_the_index_and_the_entry(tmp_path, weight_map, field,
                                                               message):
  component, index = sharded_component(tmp_path, weight_map)
  with pytest.raises(InputError, match=message) as error:
    safetensors_io.find_weight_files(component)
  assert error.value.path == str(index) and error.value.field == field


def test_shards_in_a_subfolder_of_the_component_are_read(tmp_path):
  component, _ = sharded_component(tmp_path, {"a": "part-1.safetensors",
                                              "b": "shards/./part-2.safetensors"})
  (component / "shards").mkdir()
  save_file({"b": np.full(3, 2.0, np.float32)}, component / "shards" / "part-2.safetensors")
  tensors = safetensors_io.read_safetensors(safetensors_io.find_weight_files(component))
  assert sorted(tensors) == ["a", "b"] and tensors["b"][0] == 2.0
