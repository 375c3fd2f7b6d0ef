"""Data for the bundle and training (MONAI's side: RAS arrays, voxels): dataset-folder discovery and pair dicts
(``dataset``), the transform chain (``transforms``: checked loading, orientation, intensity, padding, resizing),
training augmentation (``augmentation``), skipping damaged subjects in a workflow (``screening``), and the demo's
synthetic subject with a known transform (``synthetic``). Built on :mod:`monai_probreg.spatial` (geometry, checks,
intensity scale), which never imports from here.
"""
