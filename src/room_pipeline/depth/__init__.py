"""Monocular depth: metrics, estimators (physics baseline, small CNN, Hugging Face, external) and their registry."""
