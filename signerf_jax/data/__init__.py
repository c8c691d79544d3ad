"""Datasets: readers, writers and synthetic scenes with ground truth."""

from signerf_jax.data.dataset import Dataset

__all__ = ["Dataset"]
