"""Images in physical space (the command line's side: ITK, LPS millimetres, native grids): reading and
validating files with their geometry (``volume_io``, ``checks``), the model grid (``model_grid``) and the intensity
scale of network inputs (``intensity``), sampling volumes at physical points (``point_sampling``), voxel/mm fields,
composition and ITK transforms (``physical``), and the ITK affine pre-alignment (``affine``). Imports nothing from
:mod:`monai_probreg.data` (which builds on it).
"""
