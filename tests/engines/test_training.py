"""monai_probreg.engines.training: what the network sees and what the loss compares, with and without augmented inputs."""

from __future__ import annotations

import torch

from monai_probreg.blocks.warp import warp_image
from monai_probreg.engines.training import RegistrationLoss, prepare_registration_batch
from monai_probreg.losses.elbo import ProbRegLoss
from monai_probreg.networks.probreg_net import RegistrationOutput


def _batch(shape=(1, 1, 8, 10, 6), with_inputs: bool = True) -> dict:
    gen = torch.Generator().manual_seed(0)
    batch = {"moving": torch.rand(shape, generator=gen), "fixed": torch.rand(shape, generator=gen)}
    if with_inputs:
        batch["moving_input"] = torch.rand(shape, generator=gen)
        batch["fixed_input"] = torch.rand(shape, generator=gen)
    return batch


def test_the_network_sees_the_augmented_inputs_when_there_are_some():
    batch = _batch()
    moving, targets, (fixed,), _ = prepare_registration_batch(batch)
    assert torch.equal(moving, batch["moving_input"]) and torch.equal(fixed, batch["fixed_input"])
    assert torch.equal(targets["moving"], batch["moving"]) and torch.equal(targets["fixed"], batch["fixed"])


def test_without_augmented_inputs_the_network_sees_the_images():
    batch = _batch(with_inputs=False)
    moving, _, (fixed,), _ = prepare_registration_batch(batch)
    assert torch.equal(moving, batch["moving"]) and torch.equal(fixed, batch["fixed"])


def _output(batch: dict, warped_source: torch.Tensor) -> RegistrationOutput:
    shape = batch["moving"].shape
    gen = torch.Generator().manual_seed(1)
    displacement = torch.randn((shape[0], 3, *shape[2:]), generator=gen)
    velocity = torch.zeros((shape[0], 3, *(n // 2 for n in shape[2:])))
    return RegistrationOutput(
        warp_image(warped_source, displacement), displacement, velocity, velocity, velocity - 2.0, None, None
    )


def test_the_likelihood_compares_the_clean_images_when_the_network_saw_augmented_ones():
    batch = _batch()
    loss = RegistrationLoss(ProbRegLoss(image_sigma=0.1, prior_lambda=1.0))
    # the network warped the augmented input; the loss must re-warp the clean moving image by the same displacement
    with_aug = loss(_output(batch, batch["moving_input"]), batch)
    clean = {k: batch[k] for k in ("moving", "fixed")}
    reference = loss(_output(clean, clean["moving"]), clean)
    assert torch.allclose(with_aug, reference, rtol=1e-6)
    naive = loss(_output(clean, batch["moving_input"]), clean)  # what the augmented warp would have scored
    assert not torch.allclose(naive, reference, rtol=1e-3)
