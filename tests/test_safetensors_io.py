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
