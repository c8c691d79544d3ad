"""The project's own small inpainting diffusion model: its procedural training and evaluation data."""
