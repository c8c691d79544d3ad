"""Checkpoints: a round trip keeps state and metadata; a damaged, truncated or foreign file and a
state of another shape are errors naming the file, unless the previous checkpoint is readable,
which is then resumed from with a warning; temporary files a killed run left behind go at the
next save."""

import flax.serialization
import numpy as np
import pytest

from signerf_jax import checkpoints
from signerf_jax.errors import InputError

STATE = {"params": {"w": np.arange(256, dtype=np.float32).reshape(16, 16)},
         "step": np.int32(7)}


def test_round_trip_keeps_the_state_and_metadata(tmp_path):
  checkpoints.save(tmp_path, STATE, {"step": 7, "seconds_trained": 1.5})
  state, metadata = checkpoints.restore(tmp_path, STATE)
  np.testing.assert_array_equal(state["params"]["w"], STATE["params"]["w"])
  assert int(state["step"]) == 7 and metadata == {"step": 7, "seconds_trained": 1.5}


def test_a_flipped_byte_is_caught_by_the_checksum(tmp_path):
  path = checkpoints.save(tmp_path, STATE, {"step": 7})
  data = bytearray(path.read_bytes())
  # Inside the array data, which keeps the file valid msgpack: only the checksum can tell.
  data[len(data) // 2] ^= 0x01
  path.write_bytes(bytes(data))
  with pytest.raises(InputError, match="damaged.*checksum") as error:
    checkpoints.restore(tmp_path, STATE)
  assert error.value.path == str(path)


@pytest.mark.parametrize("contents", [
    lambda data: data[:len(data) // 3],  # truncated
    lambda data: b"",  # empty
    lambda data: flax.serialization.msgpack_serialize({"state": {}, "metadata": {}}),  # no checksum
], ids=["truncated", "empty", "without_checksum"])
def test_an_unreadable_file_is_an_error_naming_it(tmp_path, contents):
  path = checkpoints.save(tmp_path, STATE, {"step": 7})
  path.write_bytes(contents(path.read_bytes()))
  with pytest.raises(InputError, match="not a readable checkpoint") as error:
    checkpoints.read(tmp_path)
  assert error.value.path == str(path)


def test_a_state_of_other_shapes_is_refused(tmp_path):
  checkpoints.save(tmp_path, STATE, {})
  other = {"params": {"w": np.zeros((8, 16), np.float32)}, "step": np.int32(0)}
  with pytest.raises(InputError, match="shapes do not match"):
    checkpoints.restore(tmp_path, other)


def test_a_missing_checkpoint_is_an_error():
  with pytest.raises(InputError, match="checkpoint not found"):
    checkpoints.read("/nonexistent/run")


def flip_a_byte(path):
  data = bytearray(path.read_bytes())
  data[len(data) // 2] ^= 0x01
  path.write_bytes(bytes(data))


def truncate(path):
  path.write_bytes(path.read_bytes()[:100])


@pytest.mark.parametrize("damage", [flip_a_byte, truncate, lambda path: path.unlink()],
                         ids=["flipped_byte", "truncated", "missing"])
def test_a_damaged_latest_checkpoint_falls_back_to_the_previous_with_a_warning(tmp_path, damage):
  checkpoints.save(tmp_path, STATE, {"step": 7})
  newer = {"params": {"w": STATE["params"]["w"] + 1}, "step": np.int32(8)}
  damage(checkpoints.save(tmp_path, newer, {"step": 8}))
  assert checkpoints.has_checkpoint(tmp_path)
  with pytest.warns(UserWarning, match="resuming from the previous checkpoint.*step 7"):
    state, metadata = checkpoints.restore(tmp_path, STATE)
  np.testing.assert_array_equal(state["params"]["w"], STATE["params"]["w"])
  assert metadata == {"step": 7}


def test_without_a_readable_previous_checkpoint_the_latest_ones_error_stands(tmp_path):
  checkpoints.save(tmp_path, STATE, {"step": 7})
  path = checkpoints.save(tmp_path, STATE, {"step": 8})
  flip_a_byte(path)
  flip_a_byte(tmp_path / checkpoints.PREVIOUS_NAME)
  with pytest.raises(InputError, match="damaged.*checksum") as error:
    checkpoints.read(tmp_path)
  assert error.value.path == str(path)


def test_each_save_keeps_the_one_it_replaces(tmp_path):
  for step in (1, 2, 3):
    checkpoints.save(tmp_path, STATE, {"step": step})
  assert checkpoints.read(tmp_path)[1] == {"step": 3}
  assert sorted(path.name for path in tmp_path.iterdir()) == [
      "checkpoint.msgpack", "checkpoint.previous.msgpack"]
  (tmp_path / "checkpoint.msgpack").unlink()
  with pytest.warns(UserWarning):
    assert checkpoints.read(tmp_path)[1] == {"step": 2}
