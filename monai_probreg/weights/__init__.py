"""Trained weights: safe loading (``loading``), the network-settings sidecar (``settings``), checkpoint
averaging (``averaging``) and TorchScript export (``export``).
"""
