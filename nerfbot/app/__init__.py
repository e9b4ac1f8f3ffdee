"""The ``nerfbot`` command line and the demo (docs/ARCHITECTURE.md)."""
