"""Scene-space geometry: proxy meshes, mesh depth, selections, masks, control depth, cameras."""
