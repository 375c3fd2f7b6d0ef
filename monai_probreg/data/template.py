"""A fixed image every user has: the MNI ICBM152 2009a nonlinear symmetric T1 template, as nilearn ships it.

nilearn carries the template inside its wheel (``nilearn.datasets.MNI152_FILE_PATH``: 197 x 233 x 189 voxels, 1 mm,
RAS, skull-stripped, uint8 intensities), so no download is needed and no image file is copied into this project.
``monai-probreg register`` without ``--fixed``, and the bundle's inference on a dataset folder without ``atlas/``,
register to it.

Licence notice of the template (ICBM 2009a, McConnell Brain Imaging Centre): Copyright (C) 1993-2009 Louis Collins,
McConnell Brain Imaging Centre, Montreal Neurological Institute, McGill University. Permission to use, copy, modify,
and distribute this software and its documentation for any purpose and without fee is hereby granted, provided that
the above copyright notice appear in all copies. The authors and McGill University make no representations about the
suitability of this software for any purpose. It is provided "as is" without express or implied warranty. Reference:
Fonov et al., NeuroImage 47 (2009) S102 and NeuroImage 54 (2011) 313-327.
"""

from __future__ import annotations

from pathlib import Path

from monai_probreg.utils.errors import InputError

__all__ = ["TEMPLATE_NAME", "mni152_template_path"]

TEMPLATE_NAME = "MNI ICBM152 2009a nonlinear symmetric T1, skull-stripped, 1 mm (nilearn)"


def mni152_template_path() -> Path:
    """The template file inside the installed nilearn package (imported here, only when needed: about 2 s)."""
    try:
        from nilearn.datasets import MNI152_FILE_PATH
    except ImportError as err:
        raise InputError(
            f"no fixed image given and the default template needs nilearn ({err}); install nilearn or "
            "pass a fixed image"
        ) from None
    path = Path(MNI152_FILE_PATH)
    if not path.is_file():
        raise InputError(
            f"the MNI152 template of nilearn {str(path)!r} is missing; reinstall nilearn or pass a fixed image"
        )
    return path
