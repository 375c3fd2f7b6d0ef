"""The failure set of the quality model's fit: what goes wrong with the scans users bring, applied to a moving scan.

Each perturbation takes the preprocessed moving image and label map ((1, 1, *S) on the fixed grid, intensities in
[0, 1]) and a seeded generator, and returns both. Orientation errors move image *and* labels (the anatomy is where
a wrong header puts it; the labels share the header); every other perturbation changes the image only (the anatomy
is still there, the registration has to find it):

- ``turn90_axial``, ``turn90_sagittal``: a 90-degree turn about the S or the R axis (a wrong orientation header);
- ``turn180_axial``, ``turn180_coronal``: 180 degrees about S or about A;
- ``crop``: 30-45% of the field of view blanked from one side of a random axis;
- ``missing_block``: a cube of 30-45 voxels inside the brain set to 0 (resection, a missing block of slices);
- ``lesion``: a bright sphere of radius 10-18 voxels inside the brain;
- ``noise_bias``: a strong multiplicative bias field and Gaussian noise of std 0.12-0.2, re-scaled to [0, 1];
- ``inverted``: inverted contrast inside the head (T2-like).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from monai.transforms import Rotate, ScaleIntensityRangePercentiles

from monai_probreg.spatial.intensity import LOWER_PERCENTILE, UPPER_PERCENTILE

Pair = tuple[torch.Tensor, torch.Tensor]
_rescale = ScaleIntensityRangePercentiles(LOWER_PERCENTILE, UPPER_PERCENTILE, 0.0, 1.0, clip=True)


def _uniform(g: torch.Generator, low: float, high: float) -> float:
    return low + (high - low) * float(torch.rand((), generator=g))


def _rotate(image: torch.Tensor, label: torch.Tensor, angles: tuple[float, float, float]) -> Pair:
    # MONAI Rotate about the grid centre, same size (corners leave the grid): image linear, labels nearest
    rot_image = Rotate(angles, keep_size=True, mode="bilinear", padding_mode="zeros")(image[0])
    rot_label = Rotate(angles, keep_size=True, mode="nearest", padding_mode="zeros")(label[0].float())
    return torch.as_tensor(rot_image)[None].float(), torch.as_tensor(rot_label)[None].round().to(label.dtype)


def _brain_centre(image: torch.Tensor, g: torch.Generator, margin: int) -> list[int]:
    inside = torch.nonzero(image[0, 0] > 0.2)
    point = inside[int(torch.randint(len(inside), (1,), generator=g))]
    return [min(max(int(c), margin), n - margin - 1) for c, n in zip(point, image.shape[2:])]


def crop(image: torch.Tensor, label: torch.Tensor, g: torch.Generator) -> Pair:
    axis = int(torch.randint(3, (1,), generator=g))
    n = image.shape[2 + axis]
    width = round(_uniform(g, 0.30, 0.45) * n)
    out = image.clone()
    index = [slice(None)] * 5
    index[2 + axis] = slice(0, width) if bool(torch.rand((), generator=g) < 0.5) else slice(n - width, n)
    out[tuple(index)] = 0.0
    return out, label


def missing_block(image: torch.Tensor, label: torch.Tensor, g: torch.Generator) -> Pair:
    size = int(_uniform(g, 30, 45))
    centre = _brain_centre(image, g, size // 2)
    out = image.clone()
    out[(..., *[slice(max(c - size // 2, 0), c + size // 2) for c in centre])] = 0.0
    return out, label


def lesion(image: torch.Tensor, label: torch.Tensor, g: torch.Generator) -> Pair:
    radius = _uniform(g, 10, 18)
    centre = _brain_centre(image, g, int(radius))
    axes = torch.meshgrid(*[torch.arange(n, dtype=torch.float32) for n in image.shape[2:]], indexing="ij")
    inside = sum((a - c) ** 2 for a, c in zip(axes, centre)) <= radius**2
    out = image.clone()
    out[0, 0][inside] = 1.0
    return out, label


def noise_bias(image: torch.Tensor, label: torch.Tensor, g: torch.Generator) -> Pair:
    shape = image.shape[2:]
    coarse = torch.randn((1, 1, 3, 3, 3), generator=g) * 0.5
    bias = torch.nn.functional.interpolate(coarse, size=shape, mode="trilinear", align_corners=True).exp()
    noisy = image * bias + torch.randn(image.shape, generator=g) * _uniform(g, 0.12, 0.2)
    return torch.as_tensor(_rescale(noisy[0]))[None].float(), label


def inverted(image: torch.Tensor, label: torch.Tensor, g: torch.Generator) -> Pair:
    return torch.where(image > 0.02, 1.0 - image, image), label


PERTURBATIONS: dict[str, Callable[[torch.Tensor, torch.Tensor, torch.Generator], Pair]] = {
    "turn90_axial": lambda i, lab, g: _rotate(i, lab, (0.0, 0.0, math.pi / 2)),
    "turn90_sagittal": lambda i, lab, g: _rotate(i, lab, (math.pi / 2, 0.0, 0.0)),
    "turn180_axial": lambda i, lab, g: (i.flip(2, 3), lab.flip(2, 3)),
    "turn180_coronal": lambda i, lab, g: (i.flip(2, 4), lab.flip(2, 4)),
    "crop": crop,
    "missing_block": missing_block,
    "lesion": lesion,
    "noise_bias": noise_bias,
    "inverted": inverted,
}
