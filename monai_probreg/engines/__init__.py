"""MONAI/ignite workflows: training glue (``training``), the validation metric (``validation_metric``), the
non-finite guard (``guards``), crash-safe checkpoints and resume (``checkpoints``), registering a pair with a trained
network (``registration``), the bundle's inference/evaluation outputs, handlers and score files (``outputs``,
``handlers``, ``score_files``) and multi-process sharding (``sharding``).
"""
