"""Fuzzing (fixed seeds): a valid transforms.json, checkpoint and config.gin are mutated at random,
and reading each must give either a correct result or an InputError naming the file — never
another exception (a traceback for the user), and never a file half-written."""

import json
import math
import random
import shutil

import numpy as np
import pytest

from signerf_jax import checkpoints, cli, configs
from signerf_jax.data import load_dataset
from signerf_jax.errors import InputError

NUM_CASES = 60
# Values a careless edit or a damaged file puts where another was.
REPLACEMENTS = (None, True, 0, -1, 2.5, 1e30, "", "x", "nan", [], [1, 2], {}, {"a": 1})


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
  directory = tmp_path_factory.mktemp("fuzz") / "scene"
  assert cli.main(["synthesize", "--out", str(directory),
                   "--gin_param", "synthetic_cameras.num_views = 5",
                   "--gin_param", "synthetic_cameras.image_size = 16",
                   "--gin_param", "synthetic_scene.num_meshes = 0"]) == 0
  return directory


def json_locations(value, path=()):
  """Every (path of keys and indices) inside a JSON value, containers and leaves."""
  yield path
  if isinstance(value, dict):
    for key, item in value.items():
      yield from json_locations(item, path + (key,))
  elif isinstance(value, list):
    for index, item in enumerate(value):
      yield from json_locations(item, path + (index,))


def mutate_json(meta, rng: random.Random):
  """One random edit of a JSON value: a value replaced, a key deleted or a list shortened."""
  location = rng.choice([path for path in json_locations(meta) if path])
  parent = meta
  for key in location[:-1]:
    parent = parent[key]
  kind = rng.choice(("replace", "delete", "shorten"))
  if kind == "delete":
    del parent[location[-1]]
  elif kind == "shorten" and isinstance(parent[location[-1]], list):
    del parent[location[-1]][rng.randrange(len(parent[location[-1]]) + 1):]
  else:
    parent[location[-1]] = rng.choice(REPLACEMENTS)
  return meta


def mutate_bytes(data: bytes, rng: random.Random) -> bytes:
  """Truncated, or a few bytes flipped."""
  if rng.random() < 0.5:
    return data[:rng.randrange(len(data))]
  data = bytearray(data)
  for _ in range(rng.randint(1, 4)):
    data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
  return bytes(data)


def file_listing(directory):
  return sorted((path.relative_to(directory).as_posix(), path.stat().st_size)
                for path in directory.rglob("*"))


@pytest.mark.parametrize("seed", range(NUM_CASES))
def test_a_mutated_transforms_json_loads_correctly_or_is_an_input_error(scene, tmp_path, seed):
  rng = random.Random(seed)
  copy = tmp_path / "scene"
  shutil.copytree(scene, copy)
  path = copy / "transforms.json"
  if rng.random() < 0.8:
    meta = mutate_json(json.loads(path.read_text()), rng)
    path.write_text(json.dumps(meta))
  else:
    path.write_bytes(mutate_bytes(path.read_bytes(), rng))
  before = file_listing(copy)
  try:
    dataset = load_dataset(copy, split="all")
  except InputError as error:
    assert error.path is not None and str(copy) in error.path
  else:
    assert np.all(np.isfinite(dataset.images)) and np.all(np.isfinite(
        np.asarray(dataset.cameras.camera_to_world)))
    assert 0 <= dataset.images.min() and dataset.images.max() <= 1
  assert file_listing(copy) == before  # Reading writes nothing.


@pytest.mark.parametrize("seed", range(NUM_CASES))
def test_a_mutated_checkpoint_is_always_caught(tmp_path, seed):
  rng = random.Random(seed)
  state = {"params": {"w": np.arange(64, dtype=np.float32)}, "step": np.int32(3)}
  path = checkpoints.save(tmp_path, state, {"step": 3})
  original = path.read_bytes()
  mutated = mutate_bytes(original, rng)
  if mutated == original:
    return
  path.write_bytes(mutated)
  with pytest.raises(InputError) as error:
    checkpoints.restore(tmp_path, state)
  assert error.value.path == str(path)


VALID_GIN = """\
TrainConfig.steps = 200
TrainConfig.learning_rate = 0.01
TrainConfig.max_seconds = 30.0
finetune/TrainConfig.steps = 100
CapacityRules.oversampling = 1.0
DataConfig.eval_every = 8
SelectionConfig.box_min = (0.0, 0.0, 0.0)
SelectionConfig.box_max = (1.0, 1.0, 1.0)
SheetConfig.rows = 2
GenerationOptions.strength = 0.9
EditConfig.prompt = 'a red cow'
"""
GIN_TOKENS = ("=", "(", ")", "'", "import os", "include 'x.gin'", "@", "%", "/", ".", "-",
              "None", "nan", "1e999", "[1,", "#", "\n", "TrainConfig", "steps")


def mutate_gin(text: str, rng: random.Random) -> str:
  lines = text.splitlines()
  index = rng.randrange(len(lines))
  line = lines[index]
  position = rng.randrange(len(line) + 1)
  kind = rng.choice(("insert", "delete", "token"))
  if kind == "insert":
    line = line[:position] + rng.choice(GIN_TOKENS) + line[position:]
  elif kind == "delete":
    line = line[:position] + line[position + rng.randint(1, 6):]
  else:
    name, _, _ = line.partition("=")
    line = f"{name}= {rng.choice(REPLACEMENTS)!r}"
  lines[index] = line
  return "\n".join(lines) + "\n"


@pytest.fixture
def clear_gin():
  yield
  configs.parse_gin()


@pytest.mark.parametrize("seed", range(NUM_CASES))
def test_a_mutated_config_gin_builds_valid_settings_or_is_an_input_error(tmp_path, clear_gin,
                                                                         seed):
  rng = random.Random(seed)
  path = tmp_path / "config.gin"
  path.write_text(mutate_gin(VALID_GIN, rng))
  try:
    configs.parse_gin([path])
    built = [configs.build(cls, scope) for cls in configs.configurables()
             for scope in (None, "finetune")]
  except InputError as error:
    assert error.path == str(path) or error.field  # The file, or the binding at fault.
    return
  for settings in built:  # Whatever was accepted passed every field's check.
    for value in vars(settings).values():
      assert not (isinstance(value, float) and not math.isfinite(value))
