"""The settings of the default model's training stages, and the optimizer they make.

Three stages, run in order (`stages`), each with its settings (gin: `vae_stage.<field>`,
`unet_stage.<field>`, `controlnet_stage.<field>`) and what they share (`StageSettings`: steps,
seed, the moving average of the parameters and the optimizer, AdamW with a linear warmup then
cosine decay and a global gradient-norm clip). What each stage's loss is: `losses`.
"""

from __future__ import annotations

import dataclasses

import gin
import optax


@dataclasses.dataclass(frozen=True)
class StageSettings:
  """What every stage sets (gin: `<stage>_stage.<field>`).

  Attributes:
    num_steps: optimizer steps of the stage; may be raised between runs to train on from a
      checkpoint (the learning-rate schedule then stretches to the new end).
    learning_rate: peak learning rate (AdamW), reached after `warmup_steps` linear steps, then
      cosine decay to `final_learning_rate_fraction` of it at `num_steps`.
    weight_decay: AdamW's decoupled weight decay.
    gradient_clip_norm: global gradient norm clip.
    ema_decay: decay of the parameters' exponential moving average (the exported weights);
      ramped up as min(ema_decay, (1 + step) / (10 + step)); 0 keeps the raw parameters.
    seed: seeds the stage's batches and noise.
  """

  num_steps: int = 1000
  learning_rate: float = 1e-3
  warmup_steps: int = 100
  final_learning_rate_fraction: float = 0.1
  weight_decay: float = 0.0
  gradient_clip_norm: float = 1.0
  ema_decay: float = 0.0
  seed: int = 0

  def optimizer(self) -> optax.GradientTransformation:
    """AdamW on the warmup-then-cosine learning-rate schedule, after the gradient norm clip."""
    schedule = optax.warmup_cosine_decay_schedule(
        0.0, self.learning_rate, max(self.warmup_steps, 1),
        max(self.num_steps, self.warmup_steps + 1),
        self.learning_rate * self.final_learning_rate_fraction)
    return optax.chain(optax.clip_by_global_norm(self.gradient_clip_norm),
                       optax.adamw(schedule, weight_decay=self.weight_decay))


@gin.configurable("vae_stage")
@dataclasses.dataclass(frozen=True)
class VaeStage(StageSettings):
  """The VAE stage.

  Attributes:
    batch_size: views per step.
    masked_fraction: share of views greyed out under an inpainting mask.
    kl_weight: weight of the mean per-element KL divergence.
    gradient_weight: weight of the L1 between image gradients.
    object_weight: weight of object pixels in the L1 and L2 reconstruction terms (others: 1).
    scaling_views: views whose latents set the scaling factor.
  """

  num_steps: int = 2000
  learning_rate: float = 1e-3
  batch_size: int = 32
  masked_fraction: float = 0.3
  kl_weight: float = 1e-4
  gradient_weight: float = 1.0
  object_weight: float = 1.0
  scaling_views: int = 512


@dataclasses.dataclass(frozen=True)
class DiffusionStage(StageSettings):
  """What the UNet and ControlNet stages share.

  Attributes:
    sheets_per_batch, singles_per_batch: samples of each kind per step.
    mask_kind_weights: sampling weights of `batches.mask_kinds` (silhouette, dilated_<r> for
      each radius, box).
    sheet_mode_weights: sampling weights of `batches.SHEET_MODES`.
    caption_dropout: probability of the empty prompt (classifier-free guidance).
    min_snr_gamma: Min-SNR-gamma loss weighting; 0 disables it.
    masked_loss_weight: weight of masked latent cells relative to the rest.
    masked_ground_loss_weight: further factor on the masked cells that hold no object pixel (the
      ground and background the model repaints around the object). A hazy repaint of them is
      what a difference from the original view counts as object.
    control_dropout: probability that a sample's ControlNet scale is 0 instead of 1.
  """

  sheets_per_batch: int = 6
  singles_per_batch: int = 12
  mask_kind_weights: tuple[float, ...] = (0.1, 0.1, 0.15, 0.25, 0.4)
  sheet_mode_weights: tuple[float, float, float] = (0.3, 0.35, 0.35)
  caption_dropout: float = 0.1
  min_snr_gamma: float = 5.0
  masked_loss_weight: float = 2.0
  masked_ground_loss_weight: float = 1.0
  control_dropout: float = 0.0
  ema_decay: float = 0.999


@gin.configurable("unet_stage")
@dataclasses.dataclass(frozen=True)
class UNetStage(DiffusionStage):
  """The UNet stage; `joint_controlnet` trains the ControlNet in it too (`losses`)."""

  num_steps: int = 4000
  joint_controlnet: bool = True
  control_dropout: float = 0.25
  learning_rate: float = 3e-4
  warmup_steps: int = 200


@gin.configurable("controlnet_stage")
@dataclasses.dataclass(frozen=True)
class ControlNetStage(DiffusionStage):
  """The optional ControlNet-only stage (everything else frozen)."""

  num_steps: int = 1500
  learning_rate: float = 3e-4
  warmup_steps: int = 100
  mask_kind_weights: tuple[float, ...] = (0.05, 0.05, 0.1, 0.3, 0.5)
