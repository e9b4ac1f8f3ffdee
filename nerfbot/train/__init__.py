"""Training: the trainer, run folders and checkpoint I/O, and ``--method auto``'s choices
(docs/ARCHITECTURE.md)."""
