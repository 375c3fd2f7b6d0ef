"""The ``monai-probreg`` command (``main``): one raw scan to all outputs (``pipeline``), many scans (``batch``),
the network from the bundle (``model``), the all-or-nothing output folder and its writers (``output_dir``) and the QC
figure (``qc``). Nothing here is imported at ``import monai_probreg``: the command imports what it needs, when it needs
it.
"""
