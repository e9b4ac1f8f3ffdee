"""Scores against ground truth: image metrics, depth errors, depth-mode sweeps
(docs/ARCHITECTURE.md)."""
