"""Datasets: readers, writers and synthetic scenes with ground truth."""

from signerf_jax.data.dataset import Dataset
from signerf_jax.data.load import detect_format, load_dataset
from signerf_jax.data.nerfstudio_writer import write_nerfstudio

__all__ = ["Dataset", "detect_format", "load_dataset", "write_nerfstudio"]
