"""Latent diffusion in Flax: UNet, ControlNet, AutoencoderKL, CLIP text encoder, schedulers."""
