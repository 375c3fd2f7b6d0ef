"""The posterior as uncertainty: closed-form velocity entropy and sampled displacement moments (``entropy``), the
displacement's first-order spread (``spread``), the per-voxel maps of a registration (``posterior_maps``), and the post-hoc calibration of the posterior (``calibration``:
fit, apply, the sidecar stored next to the weights).
"""
