"""Recipes that turn a trained run into a baked renderer (docs/ARCHITECTURE.md)."""
