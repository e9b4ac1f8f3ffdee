"""Rays and cameras, sampling, compositing, encodings, losses and metrics: the torch building
blocks every field and renderer shares (docs/ARCHITECTURE.md)."""
