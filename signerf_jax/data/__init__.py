"""Datasets: readers, writers and synthetic scenes with ground truth."""

from signerf_jax.data.dataset import Dataset, SceneViews
from signerf_jax.data.load import detect_format, load_dataset, load_views
from signerf_jax.data.nerfstudio_writer import write_nerfstudio

__all__ = ["Dataset", "SceneViews", "detect_format", "load_dataset", "load_views",
           "write_nerfstudio"]
