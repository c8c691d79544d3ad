"""CLIP in Flax: tokenizers, the text tower (Stable Diffusion's prompt encoder), the vision tower
and image preprocessing, and the text-image directional similarity of edits."""
