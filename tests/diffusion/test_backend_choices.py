"""Every CPU-tuned choice is made for CPUs only: GPUs and TPUs take XLA's convolutions,
`jax.nn.dot_product_attention` and XLA's default compiler options. Each backend's choice is
checked by naming the backend ("cpu", "gpu", "tpu"), without its device."""

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from signerf_jax.diffusion import attention as attention_lib
from signerf_jax.diffusion import cpu_attention, layers, sampler
from signerf_jax.diffusion.attention import AttentionOptions, attention_path

ACCELERATORS = ("gpu", "tpu")
# (x shape, kernel shape, stride, padding, compute dtype): a 1x1 convolution, a 3x3 one on a
# small map (im2col on CPUs), on maps large enough for Winograd's F(4x4) and F(2x2), an odd
# width, a strided one, and bfloat16 ones.
CONVOLUTIONS = [
    ((2, 32, 32, 64), (1, 1, 64, 64), 1, 0, jnp.float32),
    ((2, 16, 16, 64), (3, 3, 64, 64), 1, 1, jnp.float32),
    ((2, 64, 64, 64), (3, 3, 64, 64), 1, 1, jnp.float32),
    ((2, 32, 32, 64), (3, 3, 64, 64), 1, 1, jnp.float32),
    ((2, 32, 31, 64), (3, 3, 64, 64), 1, 1, jnp.float32),
    ((2, 64, 64, 64), (3, 3, 64, 64), 2, ((0, 1), (0, 1)), jnp.float32),
    ((2, 64, 64, 64), (3, 3, 64, 64), 1, 1, jnp.bfloat16),
    ((2, 32, 31, 64), (3, 3, 64, 64), 1, 1, jnp.bfloat16),
]


@pytest.mark.parametrize("backend", ACCELERATORS)
def test_gpus_and_tpus_take_xlas_convolution(backend):
  for convolution in CONVOLUTIONS:
    assert layers.convolution_algorithm(*convolution, backend=backend) == "xla"


def test_cpus_take_the_cpu_choice():
  chosen = [layers.convolution_algorithm(*convolution, backend="cpu")
            for convolution in CONVOLUTIONS]
  assert chosen == [layers.cpu_convolution_algorithm(*convolution)
                    for convolution in CONVOLUTIONS]
  assert chosen == ["matmul", "im2col", "winograd_4x4", "winograd_2x2", "xla", "xla",
                    "winograd_2x2", "im2col"]


def test_the_default_backend_is_the_one_jax_computes_on(monkeypatch):
  winograd_sized = CONVOLUTIONS[2]
  assert layers.convolution_algorithm(*winograd_sized) == "winograd_4x4"  # These tests' CPU.
  monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
  assert layers.convolution_algorithm(*winograd_sized) == "xla"


@pytest.mark.parametrize("backend, winograd", [("cpu", True), ("gpu", False), ("tpu", False)])
def test_conv2d_traces_the_backends_choice(backend, winograd):
  """A Winograd-sized convolution: on a CPU a Winograd rewrite (a custom gradient around its
  matmuls), elsewhere XLA's convolution."""
  kernel = jnp.zeros((3, 3, 64, 64))
  jaxpr = jax.make_jaxpr(lambda x: layers.conv2d(x, kernel, 1, 1, jnp.float32, backend))(
      jax.ShapeDtypeStruct((2, 64, 64, 64), jnp.float32))
  primitives = {str(equation.primitive) for equation in jaxpr.eqns}
  assert ("custom_vjp_call" in primitives) == winograd
  assert ("conv_general_dilated" in primitives) != winograd


@pytest.fixture
def kernel_loads(monkeypatch):
  """The fused kernel loads (whatever this machine can build); `calls` counts the tries."""
  calls = []
  monkeypatch.setattr(cpu_attention, "load", lambda: calls.append(True) or True)
  return calls


@pytest.mark.parametrize("head_dim, compute_dtype, cpu_kernel, expected", [
    (40, jnp.float32, True, "cpu_kernel"), (40, jnp.float32, False, "xla_chunked"),
    (40, jnp.bfloat16, True, "xla_chunked"), (12, jnp.float32, True, "xla_chunked")])
def test_attention_on_a_cpu(kernel_loads, head_dim, compute_dtype, cpu_kernel, expected):
  options = AttentionOptions(cpu_kernel=cpu_kernel)
  assert attention_path(head_dim, compute_dtype, options, "cpu") == expected


def test_attention_on_a_cpu_without_the_kernel(monkeypatch):
  monkeypatch.setattr(cpu_attention, "load", lambda: False)
  assert attention_path(40, jnp.float32, AttentionOptions(), "cpu") == "xla_chunked"


@pytest.mark.parametrize("backend", ACCELERATORS)
@pytest.mark.parametrize("compute_dtype", [jnp.float32, jnp.bfloat16])
def test_attention_on_gpus_and_tpus_is_jax_nn(kernel_loads, backend, compute_dtype):
  for options in (AttentionOptions(), AttentionOptions(cpu_kernel=False)):
    assert attention_path(40, compute_dtype, options, backend) == "jax_nn"
  assert not kernel_loads  # Never built for a GPU or TPU program.


@pytest.fixture
def library_calls(monkeypatch):
  """Records the shapes and keyword arguments of each `jax.nn.dot_product_attention` call."""
  calls = []
  library = jax.nn.dot_product_attention

  def recorded(query, key, value, **keywords):
    calls.append((query.shape, keywords))
    return library(query, key, value, **keywords)

  monkeypatch.setattr(jax.nn, "dot_product_attention", recorded)
  return calls


def test_gpu_attention_calls_jax_nn_over_query_chunks(library_calls):
  """JAX picks the implementation (none is named); 2,500 queries in chunks of at most 1,024 make
  three of 834 (two padding queries), one traced call; the result is softmax attention's."""
  keys = jax.random.split(jax.random.key(0), 3)
  query, key, value = (jax.random.normal(k, (1, tokens, 2, 8))
                       for k, tokens in zip(keys, (2500, 300, 300)))
  out = attention_lib.dot_product_attention(query, key, value, backend="gpu")
  assert library_calls == [((1, 834, 2, 8), {"scale": 1.0})]
  assert out.shape == query.shape and out.dtype == jnp.float32
  scores = jnp.einsum("bqhd,bkhd->bhqk", query, key) / np.sqrt(8)
  expected = jnp.einsum("bhqk,bkhd->bqhd", jax.nn.softmax(scores, axis=-1), value)
  np.testing.assert_allclose(out, expected, atol=1e-5, rtol=0)


def test_cpu_attention_does_not_call_jax_nn(library_calls):
  query = jnp.ones((1, 64, 2, 8))
  attention_lib.dot_product_attention(query, query, query, backend="cpu")
  assert not library_calls


def models(compute_dtype):
  """What `sampler.program` reads of a model set: the UNet's compute dtype."""
  return types.SimpleNamespace(unet=types.SimpleNamespace(compute_dtype=compute_dtype))


@pytest.mark.parametrize("backend", ACCELERATORS)
@pytest.mark.parametrize("compute_dtype", [jnp.float32, jnp.bfloat16])
def test_gpus_and_tpus_compile_the_sampler_with_xlas_defaults(backend, compute_dtype):
  assert sampler.program(models(compute_dtype), backend) is sampler.sample


def test_cpus_compile_the_float32_sampler_with_the_cpu_options(monkeypatch):
  float32_program = sampler.program(models(jnp.float32), "cpu")
  assert float32_program is not sampler.sample
  assert sampler.program(models(jnp.bfloat16), "cpu") is sampler.sample
  assert sampler.program(models(jnp.float32)) is float32_program  # These tests' CPU.
  monkeypatch.setattr(jax, "default_backend", lambda: "tpu")
  assert sampler.program(models(jnp.float32)) is sampler.sample
