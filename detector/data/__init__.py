"""Label-file frames, the augmentations both stages share (colour, camera) and batching."""
