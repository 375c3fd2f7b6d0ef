"""PartialVolumeLabels: the label entropy of samples read with partial volume, against a reference through MONAI's
linear warp of one-hot maps (warp_one_hot), closed forms in 2-d and 3-d, and one test per bad argument."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from monai_probreg.blocks.warp import warp_one_hot
from monai_probreg.uncertainty.partial_volume import LABEL_LIMIT, PartialVolumeLabels


def reference_entropy(labels: torch.Tensor, displacements: list[torch.Tensor]) -> torch.Tensor:
    """The same distribution by linear interpolation of each label's indicator (zeros outside: label 0 takes the
    rest), averaged over the samples."""
    count = int(labels.max()) + 1
    one_hot = F.one_hot(labels[0, 0].long(), count).movedim(-1, 0)[None].float()
    p = torch.stack([warp_one_hot(one_hot, d)[0] for d in displacements]).mean(0)
    p[0] = 1 - p[1:].sum(0)
    return -(p * p.clamp_min(1e-12).log()).sum(0)


def blocky_labels(shape, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    coarse = torch.randint(0, 5, tuple(max(1, n // 3) for n in shape), generator=generator).float()[None, None]
    mode = "nearest"
    return F.interpolate(coarse, size=shape, mode=mode).to(torch.int16)


def two_labels(shape, seed: int = 0) -> torch.Tensor:
    """Label 4 on one side of an oblique plane, 1 on the other: every cell holds one label or two."""
    del seed
    grid = torch.stack(torch.meshgrid(*[torch.arange(n, dtype=torch.float) for n in shape], indexing="ij"))
    normal = torch.tensor([1.0, 0.7, 0.4][: len(shape)]).view(-1, *[1] * len(shape))
    side = (grid * normal).sum(0) > 0.5 * float((torch.tensor(shape) * normal.flatten()).sum())
    return torch.where(side, 4, 1).to(torch.int16)[None, None]


def noisy_labels(shape, seed: int = 0) -> torch.Tensor:
    """A label drawn per voxel: most cells hold three labels or more."""
    generator = torch.Generator().manual_seed(seed)
    return torch.randint(0, 6, (1, 1, *shape), generator=generator, dtype=torch.int16)


@pytest.mark.parametrize("scale", [0.3, 1.5])  # sub-voxel: most cells read wholly; larger: more junctions
@pytest.mark.parametrize("make", [blocky_labels, two_labels, noisy_labels])
@pytest.mark.parametrize("shape", [(9, 11), (7, 8, 9)])
def test_entropy_matches_the_linear_warp_of_one_hot_maps(shape, make, scale):
    labels = make(shape)
    generator = torch.Generator().manual_seed(1)
    displacements = [torch.randn((1, len(shape), *shape), generator=generator) * scale for _ in range(5)]
    reader = PartialVolumeLabels(labels)
    for d in displacements:
        reader.add(d)
    entropy = reader.entropy()
    assert entropy.shape == shape and entropy.dtype == torch.float32
    assert torch.allclose(entropy, reference_entropy(labels, displacements), atol=1e-5)


def test_far_outside_reads_label_zero_and_the_zero_displacement_reads_each_label_wholly():
    labels = blocky_labels((6, 7, 8), seed=2) + 1  # no label 0 inside the grid
    reader = PartialVolumeLabels(labels)
    reader.add(torch.zeros(1, 3, 6, 7, 8))
    assert torch.equal(reader.entropy(), torch.zeros(6, 7, 8))
    far = PartialVolumeLabels(labels)
    far.add(torch.full((1, 3, 6, 7, 8), 50.0))  # every point outside: label 0 for every voxel, wholly
    far.add(torch.zeros(1, 3, 6, 7, 8))
    assert torch.allclose(far.entropy(), torch.full((6, 7, 8), math.log(2)), atol=1e-6)


def test_a_half_voxel_shift_across_a_boundary_gives_log_2_there_and_0_inside():
    labels = torch.zeros(1, 1, 1, 8, dtype=torch.int16)
    labels[..., 4:] = 3
    shift = torch.zeros(1, 2, 1, 8)
    shift[0, 1] = 0.5  # every voxel reads half a voxel towards higher indices along axis 1
    reader = PartialVolumeLabels(labels)
    reader.add(shift)
    entropy = reader.entropy()[0]
    assert float(entropy[3]) == pytest.approx(math.log(2), abs=1e-6)  # between labels 0 and 3
    assert float(entropy[7]) == pytest.approx(math.log(2), abs=1e-6)  # half outside the grid: label 0
    assert torch.allclose(entropy[[0, 1, 2, 4, 5, 6]], torch.zeros(6), atol=1e-6)


def test_samples_that_disagree_wholly_give_the_entropy_of_their_labels():
    labels = torch.zeros(1, 1, 12, 12, dtype=torch.int16)
    labels[..., 6:] = 2
    reader = PartialVolumeLabels(labels)
    still, moved = torch.zeros(1, 2, 12, 12), torch.zeros(1, 2, 12, 12)
    moved[0, 1] = 3.0  # voxels 3-5 of axis 1 read label 2 wholly in this sample, label 0 in the other
    for d in (still, still, moved):
        reader.add(d)
    entropy = reader.entropy()
    expected = -(2 / 3 * math.log(2 / 3) + 1 / 3 * math.log(1 / 3))
    assert torch.allclose(entropy[:, 3:6], torch.full((12, 3), expected), atol=1e-6)
    assert torch.equal(entropy[:, :3], torch.zeros(12, 3))


@pytest.mark.parametrize(
    ("labels", "match"),
    [
        (torch.zeros(1, 2, 4, 4, dtype=torch.int16), r"expected labels \(1, 1, \*S\)"),
        (torch.zeros(1, 1, 4, dtype=torch.int16), r"expected labels \(1, 1, \*S\)"),
        (torch.full((1, 1, 4, 4), 0.5), "must hold integer values"),
        (torch.full((1, 1, 4, 4), -1, dtype=torch.int16), r"must lie in \[0, "),
        (torch.full((1, 1, 4, 4), LABEL_LIMIT, dtype=torch.int32), r"must lie in \[0, "),
    ],
)
def test_bad_labels_are_refused(labels, match):
    with pytest.raises(ValueError, match=match):
        PartialVolumeLabels(labels)


def test_a_label_map_loaded_as_floats_reads_as_its_integers():
    labels = blocky_labels((5, 6, 7), seed=3)
    shift = torch.full((1, 3, 5, 6, 7), 0.3)
    as_int, as_float = PartialVolumeLabels(labels), PartialVolumeLabels(labels.float())
    as_int.add(shift)
    as_float.add(shift)
    assert torch.equal(as_int.entropy(), as_float.entropy())


def test_a_displacement_of_another_grid_and_an_entropy_before_any_sample_are_refused():
    reader = PartialVolumeLabels(torch.zeros(1, 1, 4, 5, dtype=torch.int16))
    with pytest.raises(ValueError, match=r"expected a displacement \(1, 2, 4, 5\)"):
        reader.add(torch.zeros(1, 2, 5, 4))
    with pytest.raises(ValueError, match="no sample was added"):
        reader.entropy()
