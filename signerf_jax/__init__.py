"""signerf-jax: SIGNeRF (Scene Integrated Generation for NeRF) in JAX."""

__version__ = "0.1.0"
