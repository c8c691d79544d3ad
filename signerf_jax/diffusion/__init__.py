"""Latent diffusion in Flax: UNet, ControlNet, AutoencoderKL, schedulers, the sampler and
the inpainting pipeline (prompts are encoded by `signerf_jax.clip`)."""
