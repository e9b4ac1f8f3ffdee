"""``nerfbot bench``: sweeps of methods x budgets, one process per point (docs/ARCHITECTURE.md)."""
