"""monai_probreg.registration.network: the inverse made after the quality estimate is the one made with the maps
(and lets the velocity go); whether the answer moves outlives the displacement."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from monai_probreg import ProbRegNet
from monai_probreg.engines.registration import register_pair
from monai_probreg.registration.network import ModelMaps, add_inverse
from monai_probreg.utils.tensors import float_numpy


def _maps(displacement: np.ndarray, velocity: torch.Tensor | None = None) -> ModelMaps:
    volume = np.zeros(displacement.shape[1:], np.float32)
    return ModelMaps(displacement, None, volume, volume, volume, velocity=velocity)


def test_add_inverse_is_exp_of_minus_the_answers_velocity_and_lets_it_go():
    torch.manual_seed(0)
    network = ProbRegNet(enc_channels=(4, 4, 4, 4), dec_channels=(4, 4, 4, 4, 4)).eval()
    output = register_pair(network, torch.rand(1, 1, 16, 16, 16), torch.rand(1, 1, 16, 16, 16))
    with torch.inference_mode():
        expected = float_numpy(network.velocity_to_displacement(-output.velocity_mean, (16, 16, 16))[0])
    maps = _maps(float_numpy(output.displacement[0]), output.velocity_mean)
    add_inverse(SimpleNamespace(network=network), maps)
    assert maps.inverse.dtype == np.float32 and np.array_equal(maps.inverse, expected)
    assert maps.velocity is None
    not_asked = _maps(float_numpy(output.displacement[0]))  # RegistrationOptions(inverse=False): no velocity kept
    add_inverse(SimpleNamespace(network=network), not_asked)
    assert not_asked.inverse is None


def test_deformed_is_read_when_the_maps_are_made():
    still = _maps(np.zeros((3, 4, 4, 4), np.float32))
    moved = _maps(np.zeros((3, 4, 4, 4), np.float32) + np.float32(1e-6))
    assert not still.deformed and moved.deformed
    moved.displacement = None  # let go by the compose stage: the flag stays
    assert moved.deformed
