"""Data-parallel training: the same steps on 1, 2, 4 and 8 devices (one ray a pixel; 2 x 2 on 1
and 8), independent sample groups, and the checks on batch sizes and multi-host arguments."""

import dataclasses
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from small_nerf import SMALL_CONFIG, count_compilations, small_model

from signerf_jax import camera, ownership, parallel
from signerf_jax.errors import InputError
from signerf_jax.nerf import model as nerf_model
from signerf_jax.nerf import training_run

STEPS = 8
# Occupancy refreshes at steps 4 and 8: the grid update runs on the mesh too.
CONFIG = dataclasses.replace(SMALL_CONFIG, steps=STEPS, occupancy_warmup_steps=4)

# Runs in a process with eight CPU devices: the same run on meshes of 1, 2, 4 and 8 of them.
DEVICE_COUNTS = (1, 2, 4, 8)
# 2 x 2 rays a pixel on one device and on eight: the shard boundaries of two and four devices
# are among eight's, so they split no pixel's rays that eight keep together.
PIXEL_SAMPLES_DEVICE_COUNTS = (1, 8)
MULTI_DEVICE_TRAINING = textwrap.dedent("""
    import dataclasses
    import sys
    import jax
    import jax.numpy as jnp
    import numpy as np
    tests, output = sys.argv[1:]
    sys.path.insert(0, tests)
    from signerf_jax import parallel
    from signerf_jax.errors import InputError
    from signerf_jax.nerf import train, training_run
    from analytic_scene import sphere_dataset
    from small_nerf import count_compilations, small_model
    from test_nerf_parallel import CONFIG, DEVICE_COUNTS, PIXEL_SAMPLES_DEVICE_COUNTS, STEPS
    assert len(jax.devices()) == max(DEVICE_COUNTS)
    sphere = sphere_dataset()
    model = small_model(sphere)
    results = {}
    for count in DEVICE_COUNTS:
      mesh = parallel.device_mesh(jax.devices()[:count])
      trainer = training_run.make_trainer(sphere, model=model, config=CONFIG, mesh=mesh)
      losses = [trainer.run(until_step=step, progress=False)["loss"]
                for step in range(1, STEPS + 1)]
      leaves = jax.tree.leaves(trainer.state.variables)
      results.update({f"losses_{count}": losses,
                      f"devices_{count}": len(leaves[0].sharding.device_set)})
      results.update({f"variables_{count}_{index}": np.asarray(leaf)
                      for index, leaf in enumerate(leaves)})
      with count_compilations() as compiled:
        trainer.run(until_step=STEPS + 2, progress=False)
      results[f"compilations_{count}"] = len(compiled)
    # 2 x 2 rays a pixel: each pixel's rays are averaged before the loss, across the shards.
    sparse = dataclasses.replace(model, capacity=dataclasses.replace(model.capacity,
                                                                     pixel_samples=2))
    for count in PIXEL_SAMPLES_DEVICE_COUNTS:
      trainer = training_run.make_trainer(sphere, model=sparse, config=CONFIG,
                                          mesh=parallel.device_mesh(jax.devices()[:count]))
      results[f"pixel_samples_losses_{count}"] = [
          trainer.run(until_step=step, progress=False)["loss"] for step in range(1, STEPS + 1)]
    step_fn, _ = train._jitted_steps(model, CONFIG, mesh)
    program = step_fn.lower(trainer.state, trainer.data, jnp.float32(0)).compile().as_text()
    results.update(all_reduces=program.count("all-reduce("),
                   all_gathers=program.count("all-gather("))
    odd = dataclasses.replace(model.capacity, rays_per_batch=1001)
    try:
      training_run.make_trainer(sphere, model=dataclasses.replace(model, capacity=odd),
                                config=CONFIG)
    except InputError as error:
      results["odd_batch_field"] = error.field
    np.savez(output, **results)
""")


@pytest.mark.slow
def test_two_four_and_eight_devices_train_like_one(tmp_path):
  output = tmp_path / "runs.npz"
  environment = dict(os.environ, JAX_PLATFORMS="cpu", JAX_NUM_CPU_DEVICES=str(max(DEVICE_COUNTS)))
  result = subprocess.run([sys.executable, "-c", MULTI_DEVICE_TRAINING,
                           str(Path(__file__).parent), str(output)], env=environment,
                          capture_output=True, text=True, timeout=600, check=False)
  assert result.returncode == 0, result.stderr[-3000:]
  runs = np.load(output)
  names = sorted(name for name in runs.files if name.startswith("variables_1_"))
  assert names
  for count in DEVICE_COUNTS:
    assert int(runs[f"devices_{count}"]) == count
    assert int(runs[f"compilations_{count}"]) == 0
    np.testing.assert_allclose(runs[f"losses_{count}"], runs["losses_1"], rtol=1e-5,
                               err_msg=f"{count} devices")
    # Adam (eps 1e-15) turns the rounding of a near-zero gradient, which the devices' partial
    # sums change, into a step of up to the learning rate: a few of the grid's entries differ
    # by a small share of one step (4 devices: 21 of 16,384 entries, 2% of a step).
    for name in names:
      np.testing.assert_allclose(runs[name.replace("_1_", f"_{count}_")], runs[name],
                                 rtol=1e-4, atol=0.05 * CONFIG.learning_rate,
                                 err_msg=f"{name}, {count} devices")
  for count in PIXEL_SAMPLES_DEVICE_COUNTS:
    np.testing.assert_allclose(runs[f"pixel_samples_losses_{count}"],
                               runs["pixel_samples_losses_1"], rtol=1e-5,
                               err_msg=f"2 x 2 rays a pixel, {count} devices")
  # Eight devices reduce gradients and loss sums across devices, and each evaluates only its
  # own rays' samples: nothing is gathered from the others.
  assert int(runs["all_reduces"]) > 0 and int(runs["all_gathers"]) == 0
  assert str(runs["odd_batch_field"]) == "Capacity.rays_per_batch"


@pytest.mark.slow
def test_a_sample_group_renders_the_same_whatever_the_other_groups_hold(sphere):
  """Rays [B, A] and [B', A] with two groups: A renders the same (with a budget tight enough to
  drop rays); with one budget for the batch, B's samples crowd all of A's out."""
  base = small_model(sphere)
  variables = nerf_model.init_variables(base, jax.random.PRNGKey(0))
  batches = [camera.random_rays(jax.random.PRNGKey(seed), sphere.cameras, 256)[0]
             for seed in range(3)]
  joined = lambda first, second: jax.tree.map(lambda a, b: jnp.concatenate([a, b]), first,
                                              second)

  def second_half_renderer(groups):
    model = dataclasses.replace(base, capacity=dataclasses.replace(
        base.capacity, sample_groups=groups, samples_per_batch=2048))
    render = jax.jit(lambda rays: nerf_model.render_rays(model, variables, rays,
                                                         jax.random.PRNGKey(3),
                                                         training=True)[0])
    return lambda first: {name: np.asarray(value[256:]) for name, value in
                          render(joined(first, batches[0])).items()
                          if name in ("rgb", "ray_complete")}

  render_grouped = second_half_renderer(2)
  grouped = [render_grouped(first) for first in batches[1:]]
  assert 0.1 < np.mean(grouped[0]["ray_complete"]) < 0.9
  for name in ("rgb", "ray_complete"):
    np.testing.assert_array_equal(grouped[0][name], grouped[1][name])
  assert not np.any(second_half_renderer(1)(batches[1])["ray_complete"])


@pytest.mark.slow
def test_a_resumed_run_is_placed_on_the_mesh_and_compiles_nothing(sphere, tmp_path):
  model = small_model(sphere)
  config = dataclasses.replace(CONFIG, steps=3)
  first = training_run.make_trainer(sphere, model=model, config=config)
  with ownership.claimed(tmp_path, ownership.RUN):  # As `training_run.train` does.
    training_run.write_model_file(tmp_path, model, sphere)
    first.run(until_step=2, run_dir=tmp_path, progress=False)
  with count_compilations() as compiled:
    resumed = training_run.train(sphere, tmp_path, model=model, config=config, progress=False)
  assert resumed.step == 3 and compiled == []


def test_sample_groups_must_split_the_batch(sphere):
  model = small_model(sphere)
  model = dataclasses.replace(model, capacity=dataclasses.replace(model.capacity,
                                                                  sample_groups=3))
  trainer = training_run.make_trainer(sphere, model=model, config=CONFIG)
  with pytest.raises(InputError) as error:
    trainer.run(until_step=1, progress=False)
  assert error.value.field == "Capacity.sample_groups"


@pytest.mark.parametrize("address, processes, process_id, field", [
    ("localhost", 2, 0, "coordinator_address"),
    ("localhost:port", 2, 0, "coordinator_address"),
    ("10.0.0.1:1234", 0, 0, "num_processes"),
    ("10.0.0.1:1234", 2, 2, "process_id"),
    ("10.0.0.1:1234", 2, -1, "process_id"),
])
def test_initialize_distributed_names_the_bad_argument(address, processes, process_id, field):
  with pytest.raises(InputError) as error:
    parallel.initialize_distributed(address, processes, process_id)
  assert error.value.field == field
