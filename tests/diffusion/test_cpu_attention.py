"""The fused CPU attention kernel: it builds here, equals softmax attention on hard shapes and
magnitudes, batches under vmap, is picked only where it applies, and a failed build is reported."""

import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.diffusion import cpu_attention
from signerf_jax.diffusion.attention import AttentionOptions, dot_product_attention
from tests.diffusion.test_attention import random_qkv, reference_attention

pytestmark = pytest.mark.skipif(cpu_attention.unmet_requirement() is not None,
                                reason=str(cpu_attention.unmet_requirement()))
kernel = jax.jit(cpu_attention.attention)


def scaled(query):
  return query * query.shape[-1] ** -0.5


def assert_within_float32_rounding(query, key, value):
  """The kernel against float64 softmax attention, within what float32 rounding of the scores
  allows: an error of eps * |score| in a score moves the output by up to that times |value|
  (2e-5 for this file's inputs of scale 3, 1e-3 at scale 30; XLA's ops err as much)."""
  expected = reference_attention(query, key, value)
  scores = np.einsum("bqhd,bkhd->bhqk", *(np.asarray(x, np.float64) for x in (query, key)))
  bound = (4 * np.finfo(np.float32).eps * np.abs(scores).max() / np.sqrt(query.shape[-1])
           * np.abs(np.asarray(value)).max() + 1e-6)
  out = np.asarray(kernel(scaled(query), key, value))
  assert np.isfinite(out).all()
  np.testing.assert_allclose(out, expected, atol=bound, rtol=0)


def test_builds_and_registers_on_this_machine():
  assert cpu_attention.load()


@pytest.mark.slow
@pytest.mark.parametrize("head_dim", [8, 16, 40, 64, 80, 160])
@pytest.mark.parametrize("query_tokens, key_tokens", [(1, 1), (63, 95), (65, 97), (513, 300)])
def test_matches_softmax_attention(head_dim, query_tokens, key_tokens):
  """Head sizes with output remainders of 0, 2 and 4 rows (of 6); token counts one short of and
  one over the 64-query / 96-key blocks, and queries split into several thread-pool tasks."""
  assert_within_float32_rounding(*random_qkv(query_tokens, key_tokens, heads=2, head_dim=head_dim))


@pytest.mark.parametrize("scale", [0.0, 1e-3, 30.0])
def test_zero_tiny_and_huge_scores(scale):
  """Zero scores (uniform weights: the mean value), tiny ones, and scores in the thousands (a
  missing maximum shift overflows exp; row gaps beyond 87 hit the kernel's exp floor)."""
  query, key, _ = random_qkv(70, 200, head_dim=16, scale=scale)
  assert_within_float32_rounding(query, key, random_qkv(70, 200, head_dim=16, seed=1)[2])


def test_a_maximum_that_moves_in_the_last_key_block():
  """The last of four key blocks (keys 288-299) holds the largest scores of two thirds of the
  queries: their weights so far must be rescaled that late, while other queries in the same
  8-query vector keep their maximum (the kernel skips the rescale only where none moved)."""
  query, key, value = random_qkv(70, 300, head_dim=16)
  key = key.at[:, 288:].multiply(2.0)
  scores = np.einsum("bqhd,bkhd->bhqk", query, key)
  moved = scores[..., 288:].max(-1) > scores[..., :288].max(-1)
  assert 0.25 < moved.mean() < 0.75
  assert_within_float32_rounding(query, key, value)


def test_vmap_adds_a_batch_axis_the_kernel_folds_in():
  query, key, value = random_qkv(65, 97, head_dim=16)
  stacked = [jnp.stack([x, 2 * x]) for x in (query, key, value)]
  out = jax.vmap(kernel)(*stacked)
  for index in range(2):
    np.testing.assert_array_equal(out[index], kernel(*(x[index] for x in stacked)))


def test_nested_vmap_with_an_unbatched_argument():
  query, key, value = random_qkv(33, 40, head_dim=8)
  queries = jnp.stack([jnp.stack([query, -query, 2 * query])] * 2)
  out = jax.vmap(jax.vmap(kernel, (0, None, None)), (0, None, None))(queries, key, value)
  assert out.shape == (2, 3, *query.shape)
  np.testing.assert_array_equal(out[1, 2], kernel(2 * query, key, value))


# Runs in a process with four CPU devices: a batch-sharded call keeps each device to its own
# batch entries (no all-gather in the compiled program) and equals the one-device result.
SHARDED_CALL = textwrap.dedent("""
    import sys
    import jax
    import numpy as np
    from jax.sharding import Mesh, NamedSharding, PartitionSpec
    from signerf_jax.diffusion import cpu_attention
    assert len(jax.devices()) == 4
    random = np.random.default_rng(0)
    query, key, value = (random.standard_normal((4, 100, 2, 16)).astype(np.float32)
                         for _ in range(3))
    sharding = NamedSharding(Mesh(np.array(jax.devices()), ("batch",)), PartitionSpec("batch"))
    sharded = jax.jit(cpu_attention.attention, in_shardings=sharding, out_shardings=sharding)
    hlo = sharded.lower(query, key, value).compile().as_text()
    out = sharded(query, key, value)
    alone = [jax.jit(cpu_attention.attention)(query[i:i + 1], key[i:i + 1], value[i:i + 1])
             for i in range(4)]
    np.testing.assert_array_equal(np.asarray(out), np.concatenate(alone))
    print(hlo.count("all-gather"), len(out.sharding.device_set))
""")


@pytest.mark.slow
def test_a_batch_sharded_call_runs_each_device_on_its_own_entries():
  environment = dict(os.environ, JAX_PLATFORMS="cpu", JAX_NUM_CPU_DEVICES="4")
  result = subprocess.run([sys.executable, "-c", SHARDED_CALL], env=environment,
                          capture_output=True, text=True, timeout=300, check=False)
  assert result.returncode == 0, result.stderr[-3000:]
  assert result.stdout.split() == ["0", "4"]


def test_results_are_deterministic():
  """Threads take tasks in any order, but each task's sums run in one fixed order."""
  query, key, value = random_qkv(600, 300, heads=4, head_dim=40)
  first = np.asarray(kernel(scaled(query), key, value))
  np.testing.assert_array_equal(first, kernel(scaled(query), key, value))


@pytest.mark.parametrize("head_dim, compute_dtype, cpu_kernel, expected", [
    (40, jnp.float32, True, True), (40, jnp.float32, False, False),
    (40, jnp.bfloat16, True, False), (12, jnp.float32, True, False),
    (168, jnp.float32, True, False)])
def test_attention_takes_the_kernel_only_where_it_applies(head_dim, compute_dtype, cpu_kernel,
                                                          expected):
  query, key, value = random_qkv(16, 16, head_dim=head_dim)
  options = AttentionOptions(cpu_kernel=cpu_kernel)
  hlo = jax.jit(dot_product_attention, static_argnums=(3, 4)).lower(
      query, key, value, options, compute_dtype).as_text()
  assert (cpu_attention.TARGET_NAME in hlo) == expected


def test_kernel_rejects_a_head_size_it_cannot_take():
  query, key, value = random_qkv(8, 8, head_dim=12)
  with pytest.raises(Exception, match="multiple of 8"):
    jax.block_until_ready(kernel(query, key, value))


def test_a_failed_build_names_the_command_and_leaves_no_file(tmp_path, monkeypatch):
  monkeypatch.setenv("SIGNERF_JAX_CACHE", str(tmp_path))
  with pytest.raises(RuntimeError, match="false"):
    cpu_attention.build(cpu_attention.SOURCE.read_text(), ["false"], "cpu")
  assert not list(tmp_path.iterdir())


@pytest.mark.slow
def test_a_build_is_cached_under_a_key_of_source_and_cpu(tmp_path, monkeypatch):
  monkeypatch.setenv("SIGNERF_JAX_CACHE", str(tmp_path))
  source = cpu_attention.SOURCE.read_text()
  library = cpu_attention.build(source, cpu="cpu A")
  built = library.stat().st_mtime_ns
  assert cpu_attention.build(source, cpu="cpu A") == library
  assert library.stat().st_mtime_ns == built
  assert cpu_attention.build(source, cpu="cpu B") != library
  assert cpu_attention.build(source + "\n// another source", cpu="cpu A") != library
  assert sorted(path.suffix for path in tmp_path.iterdir()) == [".so"] * 3
