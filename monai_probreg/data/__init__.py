"""Data for the bundle and training (MONAI's side: RAS arrays, voxels): dataset-folder discovery and pair dicts
(``dataset``), the transform chain (``transforms``: checked loading, orientation, intensity, padding, resizing),
training augmentation (``augmentation``), and skipping damaged subjects in a workflow (``screening``).
"""
