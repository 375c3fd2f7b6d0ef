"""Images in physical space (the command line's side: ITK, LPS millimetres, native grids): reading and
validating files with their geometry (``volume_io``, ``checks``), the model grid (``model_grid``), sampling volumes at
physical points (``point_sampling``), voxel/mm fields, composition and ITK transforms (``physical``), and the ITK
affine pre-alignment (``affine``).
"""
