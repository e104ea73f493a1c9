"""Patient anatomy: phantom generation, segmentation, signed distance, surface mesh."""
