"""Images synthesised from whole-head label maps: training anatomy beyond one dataset (SynthMorph's recipe).

Hoffmann et al. (SynthMorph, IEEE TMI 2022) train registration on images rendered from label maps: one random
intensity per label, so the network meets many anatomies and contrasts. Here the label maps are FreeSurfer-labelled
whole heads (the SynthSeg repository's ``training_label_maps``: brain structures, CSF, and extra-cerebral classes
500+ for skull, scalp, eyes...). Two renderings:

- **T1-like** (:data:`T1_LIKE`): each brain structure at its usual T1-weighted brightness relative to cerebral white
  matter (1.0), jittered per draw by ``jitter`` (a relative standard deviation); labels the table does not know
  (the extra-cerebral classes, lesions) get a uniform random intensity in [0, 1];
- **T2-like** (:data:`T2_LIKE`, for benchmarks of a second contrast): fluid bright, white matter dark;
- **random** (with probability ``random_prob``): every label uniform in [0, 1], SynthMorph's contrast-agnostic draw.

One intensity table is drawn per *pair* and used for both images, so the Gaussian image likelihood still compares
one contrast on both sides (as the intensity augmentation of :mod:`monai_probreg.data.augmentation` keeps the clean
images); independent per-voxel texture noise and a partial-volume blur are then drawn per image, and each image is
scaled to [0, 1] by the preprocessing's percentiles. The network-input augmentation (bias, gamma, blur, noise) runs
after this, as for real scans.

Written here: MONAI has no label-to-image synthesis; SynthSeg's generator is TensorFlow and its own priors do not
index these label values. The table is ours (typical 1.5-3 T MPRAGE ratios), not fitted to any dataset.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from monai.transforms import GaussianSmooth, MapTransform, RandomizableTransform, ScaleIntensityRangePercentiles

from monai_probreg.data.dataset import IMAGE_KEYS, LABEL_KEYS
from monai_probreg.spatial.intensity import LOWER_PERCENTILE, UPPER_PERCENTILE

__all__ = ["ASEG_LABELS", "T1_LIKE", "T2_LIKE", "RandLabelContrastd", "SlotLabelsd", "render_labels", "scale_to_unit"]

# FreeSurfer label -> (T1-weighted intensity relative to cerebral white matter, T2-weighted intensity relative to CSF),
# left and right alike. T2: fluid bright, white matter darkest of the tissues, the iron-rich pallidum dark, vessels a
# flow void (typical 1.5-3 T MPRAGE and turbo spin echo ratios, not fitted to any dataset); the T2 column is for
# cross-contrast pairs (a T2-weighted scan onto a T1-weighted atlas: benchmarks/cross_contrast.py)
_BILATERAL = {  # (left, right): (T1, T2)
    (2, 41): (1.00, 0.30),  # cerebral white matter
    (3, 42): (0.62, 0.50),  # cerebral cortex
    (4, 43): (0.18, 1.00),  # lateral ventricle
    (5, 44): (0.20, 0.95),  # inferior lateral ventricle
    (7, 46): (0.95, 0.32),  # cerebellum white matter
    (8, 47): (0.66, 0.52),  # cerebellum cortex
    (10, 49): (0.86, 0.40),  # thalamus
    (11, 50): (0.72, 0.50),  # caudate
    (12, 51): (0.76, 0.44),  # putamen
    (13, 52): (0.88, 0.33),  # pallidum
    (17, 53): (0.63, 0.56),  # hippocampus
    (18, 54): (0.66, 0.54),  # amygdala
    (26, 58): (0.70, 0.50),  # accumbens
    (28, 60): (0.88, 0.38),  # ventral diencephalon
    (30, 62): (0.55, 0.15),  # vessel
}
# 3rd and 4th ventricle, brainstem, CSF, 5th ventricle, optic chiasm
_MIDLINE = {14: (0.18, 1.00), 15: (0.18, 1.00), 16: (0.90, 0.36), 24: (0.18, 1.00), 72: (0.18, 1.00), 85: (0.90, 0.35)}


def _column(k: int) -> dict[int, float]:
    return {
        **{lab: values[k] for pair, values in _BILATERAL.items() for lab in pair},
        **{lab: values[k] for lab, values in _MIDLINE.items()},
    }


T1_LIKE: dict[int, float] = _column(0)
T2_LIKE: dict[int, float] = _column(1)

# the structures Dice is scored on (FreeSurfer's aseg as SynthMorph reports it): the table less vessels, the 5th
# ventricle and the chiasm (tens of voxels at 1 mm: no overlap measure is stable on them)
ASEG_LABELS: tuple[int, ...] = tuple(sorted(set(T1_LIKE) - {30, 62, 72, 85}))


def scale_to_unit(
    image: torch.Tensor, lower: float = LOWER_PERCENTILE, upper: float = UPPER_PERCENTILE
) -> torch.Tensor:
    """Intensities at the ``lower``/``upper`` percentiles -> 0 and 1, clipped: MONAI's
    ``ScaleIntensityRangePercentiles``, as the preprocessing scales a scan."""
    scale = ScaleIntensityRangePercentiles(lower=lower, upper=upper, b_min=0.0, b_max=1.0, clip=True)
    return torch.as_tensor(scale(image.float()), dtype=torch.float32)


def render_labels(
    labels: torch.Tensor,
    table: Mapping[int, float],
    texture_std: float = 0.0,
    blur_sigma: float = 0.0,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """An image of the integer map ``labels`` (C, *S): ``table[label]`` per voxel (0 for labels it lacks, the
    background among them), plus Gaussian texture noise of ``texture_std``, blurred by a Gaussian of ``blur_sigma``
    voxels (partial volume; MONAI ``GaussianSmooth``), then scaled to [0, 1] (:func:`scale_to_unit`).
    Returns float32, the shape of ``labels``.
    """
    if labels.ndim < 3:
        raise ValueError(f"labels must be (C, *S) with 2 or 3 spatial axes; got shape {tuple(labels.shape)}")
    values = labels.long()
    if int(values.min()) < 0:
        raise ValueError(f"labels must be non-negative integers; got minimum {int(values.min())}")
    lut = torch.zeros(int(values.max()) + 1, dtype=torch.float32)
    for label, intensity in table.items():
        if 0 < int(label) < lut.numel():
            lut[int(label)] = float(intensity)
    image = lut[values]
    if texture_std > 0:
        noise = torch.randn(image.shape, generator=generator) * texture_std
        image = image + noise * (values > 0)
    if blur_sigma > 0:
        image = GaussianSmooth(sigma=blur_sigma)(image)
    return scale_to_unit(image)


class SlotLabelsd(MapTransform):
    """Relabel ``keys``: ``structures[k] -> slots[k]``, every other value -> 0 (no structure of the Dice term).

    The Dice term one-hot encodes a fixed list of label values (:class:`~monai_probreg.engines.training.
    RegistrationLoss`). A pair's two maps always come from one dataset, so a value is only a *slot* that means one
    structure within a pair: mapping another dataset's structures onto the first slots of the list keeps the number
    of channels, and the Dice term's weight per structure, as they are for the dataset the list was made for.
    MONAI's ``MapLabelValued`` keeps values it is not given, and a FreeSurfer value left as it is could fall on
    another dataset's slot (163, say, is a label of both LPBA40 and SynthSeg's maps), hence this transform.
    """

    def __init__(self, keys: Sequence[str], structures: Sequence[int], slots: Sequence[int]) -> None:
        super().__init__(keys)
        if len(structures) > len(slots) or len(set(structures)) != len(structures):
            raise ValueError(
                f"expected at most {len(slots)} distinct structures for {len(slots)} slots; got {list(structures)}"
            )
        if any(int(v) < 0 for v in (*structures, *slots)):
            raise ValueError(f"structures and slots must be non-negative; got {list(structures)} and {list(slots)}")
        self.structures = [int(v) for v in structures]
        self.slots = [int(v) for v in slots[: len(structures)]]

    def __call__(self, data: dict) -> dict:  # type: ignore[override]
        d = dict(data)
        for key in self.key_iterator(d):
            labels = torch.as_tensor(d[key])
            top = max(int(labels.max()), max(self.structures, default=0)) + 1
            lut = torch.zeros(top, dtype=torch.long)
            lut[torch.tensor(self.structures, dtype=torch.long)] = torch.tensor(self.slots, dtype=torch.long)
            out = lut[labels.long().clamp(min=0)].to(labels.dtype)
            d[key] = d[key].__class__(out, meta=d[key].meta) if hasattr(d[key], "meta") else out
        return d


class RandLabelContrastd(RandomizableTransform, MapTransform):
    """Replace each image of a pair by a rendering of its label map (module docstring), one table per call.

    Args:
        image_keys, label_keys: the images written and the label maps (C, *S) they are rendered from, in order.
        prob: probability that the pair is re-rendered (else it is returned unchanged).
        random_prob: probability that the table is SynthMorph's uniform random contrast rather than T1-like.
        jitter: relative standard deviation of the T1-like intensities, drawn per label.
        texture_std: standard deviation of the per-voxel noise before the blur (intensity units of the table).
        blur_sigma: range (low, high) of the partial-volume blur, voxels, drawn per image.
    """

    def __init__(
        self,
        image_keys: Sequence[str] = IMAGE_KEYS,
        label_keys: Sequence[str] = LABEL_KEYS,
        prob: float = 1.0,
        random_prob: float = 0.25,
        jitter: float = 0.08,
        texture_std: float = 0.03,
        blur_sigma: Sequence[float] = (0.3, 0.8),
    ) -> None:
        MapTransform.__init__(self, list(label_keys))
        RandomizableTransform.__init__(self, prob)
        if len(image_keys) != len(label_keys) or not image_keys:
            raise ValueError(f"expected one label key per image key; got {list(image_keys)} and {list(label_keys)}")
        if not 0.0 <= random_prob <= 1.0 or jitter < 0 or texture_std < 0:
            raise ValueError(
                f"expected random_prob in [0, 1], jitter >= 0 and texture_std >= 0; got {random_prob!r}, "
                f"{jitter!r}, {texture_std!r}"
            )
        if len(blur_sigma) != 2 or not 0.0 <= float(blur_sigma[0]) <= float(blur_sigma[1]):
            raise ValueError(f"blur_sigma must be a range (low, high) with 0 <= low <= high; got {blur_sigma!r}")
        self.image_keys, self.label_keys = tuple(image_keys), tuple(label_keys)
        self.random_prob, self.jitter, self.texture_std = float(random_prob), float(jitter), float(texture_std)
        self.blur_sigma = (float(blur_sigma[0]), float(blur_sigma[1]))

    def draw_table(self, labels: Sequence[int]) -> dict[int, float]:
        """One intensity per non-zero label of ``labels`` (module docstring)."""
        if self.R.uniform() < self.random_prob:
            return {int(v): float(self.R.uniform()) for v in labels if v > 0}
        return {
            int(v): (
                T1_LIKE[int(v)] * (1.0 + self.jitter * float(self.R.standard_normal()))
                if int(v) in T1_LIKE
                else float(self.R.uniform())
            )
            for v in labels
            if v > 0
        }

    def __call__(self, data: dict) -> dict:  # type: ignore[override]
        d = dict(data)
        self.randomize(None)
        if not self._do_transform:
            return d
        maps = [torch.as_tensor(d[k]) for k in self.label_keys]
        table = self.draw_table(sorted({int(v) for m in maps for v in torch.unique(m).tolist()}))
        generator = torch.Generator().manual_seed(int(self.R.randint(0, 2**31 - 1)))
        for image_key, labels in zip(self.image_keys, maps):
            sigma = float(self.R.uniform(*self.blur_sigma))
            image = render_labels(labels, table, self.texture_std, sigma, generator)
            old = d.get(image_key)
            d[image_key] = old.__class__(image, meta=old.meta) if hasattr(old, "meta") else image
        return d
