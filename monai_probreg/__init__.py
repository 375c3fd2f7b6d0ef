"""monai_probreg: probabilistic diffeomorphic registration (Dalca et al., MICCAI 2018) as MONAI components.

Conventions, written once for the whole package (docs/design.md, "Conventions", repeats them with examples):

1. Images are (B, C, *S); fields (velocity, displacement) are (B, spatial_dims, *S). Channel k of a field
   is the component along tensor axis 2 + k (no xyz flip anywhere else in our code: the single flip to
   ``grid_sample``'s xyz order is :mod:`monai_probreg.blocks.grid_coords`, or MONAI's ``Warp`` on its own path).
2. Fields are in voxels of the grid they live on: velocities on the velocity grid (image / int_downsize),
   displacements returned by the model on the image grid.
3. Warping pulls back: ``warped[x] = moving[x + displacement[x]]``, linear interpolation with voxel centres
   at integer indices (``align_corners=True``). A positive displacement along axis k samples from higher
   indices along k, so image content moves towards lower indices.
4. The moving image is warped into the fixed image's grid (MONAI's convention). In the paper's notation
   (``x ~ N(y o phi_z, sigma^2 I)``) our moving = y and our fixed = x.
5. ``log_var`` is always a log-variance, log sigma^2.
"""

from monai_probreg.blocks.integration import (
    DisplacementResize,
    ScalingAndSquaring,
    integrate_velocity,
    resize_displacement,
)
from monai_probreg.blocks.sampling import VelocitySampler, sample_velocity
from monai_probreg.blocks.warp import (
    CachedWarp,
    SpatialTransformer,
    compose_displacements,
    warp_image,
    warp_labels,
    warp_one_hot,
)
from monai_probreg.losses.elbo import LossTerms, ProbRegLoss
from monai_probreg.losses.kl import LaplacianKLLoss, laplacian_kl, neighbour_degree
from monai_probreg.losses.likelihood import GaussianImageLoss, gaussian_image_loss, make_image_loss
from monai_probreg.metrics.dice import label_dice
from monai_probreg.metrics.jacobian import JacobianStats, jacobian_determinant, jacobian_stats
from monai_probreg.networks.probreg_net import PosteriorSamples, ProbRegNet, RegistrationOutput
from monai_probreg.networks.velocity_unet import VelocityPosterior, VelocityUNet
from monai_probreg.uncertainty.calibration import calibrate_log_var
from monai_probreg.uncertainty.entropy import (
    DisplacementUncertainty,
    displacement_uncertainty,
    label_entropy,
    velocity_entropy,
)
from monai_probreg.uncertainty.partial_volume import PartialVolumeLabels

__version__ = "0.35.0"  # the bundle release (bundle/configs/metadata.json "version"); pyproject reads it

__all__ = [
    "CachedWarp",
    "DisplacementResize",
    "DisplacementUncertainty",
    "GaussianImageLoss",
    "JacobianStats",
    "LaplacianKLLoss",
    "LossTerms",
    "PartialVolumeLabels",
    "PosteriorSamples",
    "ProbRegLoss",
    "ProbRegNet",
    "RegistrationOutput",
    "ScalingAndSquaring",
    "SpatialTransformer",
    "VelocityPosterior",
    "VelocitySampler",
    "VelocityUNet",
    "calibrate_log_var",
    "compose_displacements",
    "displacement_uncertainty",
    "gaussian_image_loss",
    "integrate_velocity",
    "jacobian_determinant",
    "label_entropy",
    "jacobian_stats",
    "label_dice",
    "laplacian_kl",
    "make_image_loss",
    "neighbour_degree",
    "resize_displacement",
    "sample_velocity",
    "velocity_entropy",
    "warp_image",
    "warp_labels",
    "warp_one_hot",
]
