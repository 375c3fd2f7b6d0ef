"""What each file of a registration's output folder is, written once: :data:`OUTPUT_FILES` (name -> meaning, and the
option or command that makes it, in brackets), which the folder carries as ``README.txt`` (:data:`OUTPUTS_README`)
and ``monai-probreg --help`` lists (:func:`output_list`). No imports: the command's help reads it without loading the
registration."""

from __future__ import annotations

__all__ = ["OUTPUT_FILES", "OUTPUTS_README", "output_list"]

# name -> what it is; the order of the README and of summary.json["outputs"]
OUTPUT_FILES = {
    "warped.nii.gz": "moving image resampled onto the fixed grid through the composed transform (linear, original "
    "intensities, 0 outside the moving scan)",
    "warped_label.nii.gz": "moving labels on the fixed grid (nearest neighbour) [--moving-label]",
    "warp.nii.gz": "composed displacement field fixed -> moving (affine + deformable), LPS mm, on the fixed grid; "
    "ITK DisplacementFieldTransform / antsApplyTransforms -t warp.nii.gz",
    "inverse_warp.nii.gz": "composed inverse field moving -> fixed, LPS mm, on the moving grid; "
    "antsApplyTransforms -i FIXED -r MOVING -t inverse_warp.nii.gz",
    "affine.tfm": "the affine part alone (fixed -> moving, ITK AffineTransform_double_3_3 text file)",
    "fixed_label_in_moving.nii.gz": "fixed labels mapped onto the moving scan's own grid (nearest neighbour) "
    "[--fixed-label]",
    "jacobian.nii.gz": "det(I + grad u) of the deformable part on the fixed grid (<= 0: folding); the composed "
    "transform's Jacobian is this times summary.json affine.determinant",
    "entropy.nii.gz": "entropy of the velocity posterior q(z) (Dalca et al. 2018, Eq. 8), fixed grid",
    "displacement_std.nii.gz": "std of the displacement under the calibrated posterior, first order (no sampling), "
    "sqrt(sum of the 3 variances), mm; "
    "a component's calibrated 95% interval is +- summary.json model.posterior_interval_95_half_width_std times that "
    "component's own std (about this map / sqrt(3)), Student-t tails [--samples K]",
    "subject.nii.gz": "the synthetic subject registered (the moving image), made from the template [demo]",
    "true_warp.nii.gz": "the known field fixed -> moving the subject was made with, LPS mm, on the fixed grid, in "
    "warp.nii.gz's convention: the answer warp.nii.gz is scored against [demo]",
    "qc.png": "quality-control figure: three orthogonal slices of each map",
    "summary.json": "timings per stage, affine, |J| <= 0 count, Dice per label, inputs and settings",
    "README.txt": "this list",
}

OUTPUTS_README = (
    "Outputs of monai-probreg register (VoxelMorph-diff, Dalca et al. 2018).\n"
    + "\n".join(f"  {name:<30}{text}" for name, text in OUTPUT_FILES.items())
    + """
Conventions: physical points are ITK's LPS millimetres. A displacement field maps a point p of its grid to
p + d(p) in the other space (ITK DisplacementFieldTransform, ANTs warp files): warp.nii.gz pulls the moving image
back onto the fixed grid, warped(p) = moving(p + d(p)). Files on the fixed grid carry the fixed image's header.
"""
)


def output_list() -> list[str]:
    """The files a registration writes besides ``README.txt``, in :data:`OUTPUT_FILES`' order, each with the option
    or command that makes it when its meaning ends with one in brackets (``warped_label.nii.gz [--moving-label]``)."""
    names = []
    for name, text in OUTPUT_FILES.items():
        if name != "README.txt":
            condition = text[text.rindex("[") :] if text.endswith("]") else ""
            names.append(f"{name} {condition}".rstrip())
    return names
