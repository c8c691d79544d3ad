"""Editing: the reference sheet, tiles cut around the selection, and the per-view slot update."""
