"""Guidance: the ControlNet's conditioning scale per step, as diffusers' controlnet_keep."""

import numpy as np
import pytest

from signerf_jax.diffusion import guidance as guidance_lib
from signerf_jax.errors import InputError


@pytest.mark.parametrize("num_steps, start, end, expected", [
    (3, 0.34, 1.0, [0, 0, 1]),  # 1/3 < 0.34: the second step is still off.
    (3, 0.0, 0.6, [1, 0, 0]),
    (4, 0.25, 0.75, [0, 1, 1, 0]),
    (2, 0.0, 1.0, [1, 1]),
])
def test_controlnet_scale_per_step_follows_diffusers_controlnet_keep(num_steps, start, end,
                                                                    expected):
  np.testing.assert_array_equal(
      guidance_lib.controlnet_conditioning_scale_per_step(num_steps, 0.7, start, end),
      0.7 * np.asarray(expected, np.float32))


@pytest.mark.parametrize("start, end", [(0.5, 0.5), (-0.1, 1.0), (0.0, 1.2)])
def test_bad_control_guidance_is_an_input_error(start, end):
  with pytest.raises(InputError):
    guidance_lib.controlnet_conditioning_scale_per_step(3, 1.0, start, end)
