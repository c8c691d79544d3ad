"""experiments/profile_diffusion.py: each XLA operation goes to the kind of work its HLO metadata
names, and a profiled forward's breakdown covers what ran."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import pytest

from signerf_jax.diffusion import layers, model_configs, weights
from signerf_jax.diffusion.unet import UNet2DCondition

UNET = "jit(unet_forward)/UNet2DCondition/UNet2DCondition.up_path/up_blocks_1"
BLOCK = f"{UNET}/attentions_0/transformer_blocks_0"


@pytest.fixture(scope="module")
def experiment(experiment_script):
  return experiment_script("profile_diffusion")


@pytest.mark.parametrize("op_name, opcode, kind", [
    (f"{UNET}/resnets_0/conv1/dot_general", "fusion", "convolution: matmuls"),
    (f"{UNET}/upsamplers_0/conv/stack", "fusion", "convolution: taps"),
    (f"{UNET}/resnets_0/conv1/convert_element_type", "fusion", "dtype conversion"),
    (f"{UNET}/resnets_0/norm1/reduce_sum", "fusion", "normalisation"),
    (f"{UNET}/conv_norm_out/mul", "fusion", "normalisation"),
    (f"{BLOCK}/attn1/while/body/closed_call/reduce_max", "fusion", "attention"),
    (f"{BLOCK}/attn2/to_k/dot_general", "fusion", "attention projections"),
    (f"{BLOCK}/attn1/to_out_0/dot_general", "fusion", "attention projections"),
    (f"{BLOCK}/ff/net_0/proj/dot_general", "fusion", "feed-forward"),
    (f"{UNET}/attentions_0/proj_in/dot_general", "fusion", "transformer projections"),
    (f"{UNET}/attentions_0/proj_in/reshape", "transpose", "layout"),
    ("jit(f)/UNet2DCondition/time_embedding/linear_1/dot_general", "fusion", "time embedding"),
    (f"{UNET}/resnets_0/add", "fusion", "other"),
])
def test_operations_go_to_the_kind_of_work_their_module_names(experiment, op_name, opcode, kind):
  assert experiment.kind_of_work(op_name, opcode) == kind


def test_instructions_are_read_from_hlo_text(experiment):
  text = ('  %fusion.3 = f32[2,4]{1,0} fusion(%p0), kind=kLoop, calls=%c, '
          'metadata={op_name="jit(f)/Tiny/conv1/dot_general" stack_frame_id=3}\n'
          '  ROOT %while.7 = (s32[], f32[4]{0}) while(%tuple.1), condition=%a, body=%b, '
          'metadata={op_name="jit(f)/Tiny/attn1/while"}\n'
          '  %constant.1 = f32[] constant(0)\n')
  assert experiment.instructions(text) == {
      "fusion.3": ("fusion", "jit(f)/Tiny/conv1/dot_general"),
      "while.7": ("while", "jit(f)/Tiny/attn1/while")}


class _Tiny(nn.Module):
  @nn.compact
  def __call__(self, x):
    return layers.Conv2d(16, name="conv1")(jax.nn.silu(x))


def test_a_profiled_forward_is_broken_down_into_shares_that_add_up(experiment):
  module = _Tiny()
  x = jnp.ones((2, 32, 32, 16))
  params = module.init(jax.random.key(0), x)
  breakdown = experiment.profile(jax.jit(module.apply), (params, x), repeats=1)
  assert breakdown["seconds"]["convolution: matmuls"] > 0
  assert sum(breakdown["share"].values()) == pytest.approx(1.0, abs=1e-3)
  assert breakdown["costliest_operations"][0]["seconds"] > 0


TINY_UNET = dict(block_out_channels=(32, 64), layers_per_block=1, norm_num_groups=8,
                 cross_attention_dim=16, attention_head_dim=2,
                 down_block_types=("CrossAttnDownBlock2D",) * 2,
                 up_block_types=("CrossAttnUpBlock2D",) * 2)


@pytest.mark.slow
@pytest.mark.parametrize("options", [
    {},
    {"mid_block_type": None},
    {"layers_per_block": 2, "down_block_types": ("CrossAttnDownBlock2D", "DownBlock2D"),
     "up_block_types": ("UpBlock2D", "CrossAttnUpBlock2D")},
    {"down_block_types": ("DownBlock2D", "CrossAttnDownBlock2D"),
     "up_block_types": ("CrossAttnUpBlock2D", "UpBlock2D")},
])
def test_transformers_are_counted_per_level_as_the_unet_builds_them(experiment, options):
  config = model_configs.UNetConfig.from_dict({**TINY_UNET, **options})
  params = jax.eval_shape(lambda: weights.random_params(UNet2DCondition(config)))
  levels = len(config.block_out_channels)
  built = [0] * levels
  for block, children in params.items():
    attentions = sum(name.startswith("attentions_") for name in children)
    if block.startswith("down_blocks_"):
      built[int(block.rsplit("_", 1)[1])] += attentions
    elif block.startswith("up_blocks_"):  # The up path runs from the lowest resolution.
      built[levels - 1 - int(block.rsplit("_", 1)[1])] += attentions
    elif block == "mid_block":
      built[-1] += attentions
  assert experiment.transformers_per_level(config) == built
  assert sum(built) > 0
