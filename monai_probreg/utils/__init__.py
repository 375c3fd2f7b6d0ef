"""Utilities with no registration knowledge, imported by every other folder and importing none of them:
atomic files (``files``), error types and one-line messages (``errors``), tensor helpers (``tensors``), process
memory reuse (``memory``), file hashes and library versions (``provenance``).
"""
