"""Renderers: a field (or a baked structure), a sampling strategy and a background, turning rays
into colours, depths and a training loss (docs/ARCHITECTURE.md)."""
