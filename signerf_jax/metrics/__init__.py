"""Image and multi-view metrics."""
