"""Background preservation: how much an edit changed the scene outside its selection mask.

The paper (appendix "Metrics") compares a render I_org of the original NeRF with a render I_edit
of the edited NeRF from the same camera, with the selection mask M of that view zeroing the edited
region in both:

  PSNR_bg = PSNR(I_org * (not M), I_edit * (not M)),   SSIM_bg = SSIM(I_org * (not M), I_edit * (not M)).

Both are averaged over all pixels of the masked images, so every selected pixel counts as a
perfect match (squared error 0, SSIM 1 away from the mask border). A large selection therefore
inflates the score: a view whose mask covers 90% of the image gains 10 dB over its background-only
PSNR. This module reports the paper's numbers as the headline (`psnr_paper`, `ssim_paper`, the
values to compare with the paper's 32.22 dB / 0.83) and, alongside, the same per-pixel quantities
averaged over the background pixels only (`psnr_background`, `ssim_background`):
  * psnr_background: 10 log10(1 / mean over background pixels of the squared error);
  * ssim_background: the SSIM map of the same masked images, averaged over background pixels (the
    Gaussian windows near the mask border still see the zeroed selection, as in the paper).

All views are processed in one jitted, vmapped call; per-view values are averaged (PSNR per view,
then the mean, as NeRF papers do). A view without background pixels has no background-only value:
it is left out of those two means (and reported as NaN per view).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from signerf_jax.metrics import image as image_metrics


def _view_metrics(original, edited, background):
  """The four metrics of one view: [H, W, 3] images, [H, W] background weights in {0, 1}."""
  masked_original = original * background[..., None]
  masked_edited = edited * background[..., None]
  has_background = jnp.sum(background) > 0
  return {
      "psnr_paper": image_metrics.psnr(masked_edited, masked_original),
      "ssim_paper": image_metrics.ssim(masked_edited, masked_original),
      "psnr_background": jnp.where(
          has_background, image_metrics.psnr(edited, original, background), jnp.nan),
      "ssim_background": jnp.where(
          has_background, image_metrics.ssim(masked_edited, masked_original, background), jnp.nan),
  }


@jax.jit
def per_view_background_preservation(original_images, edited_images, selection_masks):
  """PSNR_bg and SSIM_bg of every view, as the paper defines them and over the background only.

  Args:
    original_images: [N, H, W, 3] float in [0, 1], renders of the original NeRF.
    edited_images: [N, H, W, 3] float in [0, 1], renders of the edited NeRF (same cameras).
    selection_masks: [N, H, W] bool or float, nonzero inside the edit's selection.
  Returns:
    {"psnr_paper", "ssim_paper", "psnr_background", "ssim_background"}: [N] float32 each (dB for
    PSNR; the background-only values are NaN for views without background pixels).
  """
  original = jnp.asarray(original_images, jnp.float32)
  edited = jnp.asarray(edited_images, jnp.float32)
  background = 1.0 - (jnp.asarray(selection_masks) != 0).astype(jnp.float32)
  return jax.vmap(_view_metrics)(original, edited, background)


def background_preservation(original_images, edited_images, selection_masks) -> dict[str, float]:
  """Means over views of `per_view_background_preservation` (same arguments).

  Returns:
    psnr_paper, ssim_paper: the paper's PSNR_bg / SSIM_bg (the headline numbers);
    psnr_background, ssim_background: averaged over background pixels only (over the views that
      have background; NaN if none has);
    num_views, background_fraction (the mean share of unselected pixels).
  """
  per_view = {name: np.asarray(value)
              for name, value in per_view_background_preservation(
                  original_images, edited_images, selection_masks).items()}
  summary = {}
  for name, values in per_view.items():
    finite = values[np.isfinite(values)]
    summary[name] = float(np.mean(finite)) if finite.size else float("nan")
  summary["num_views"] = int(per_view["psnr_paper"].shape[0])
  summary["background_fraction"] = float(np.mean(np.asarray(selection_masks) == 0))
  return summary
