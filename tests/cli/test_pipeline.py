"""monai_probreg.cli.pipeline internals: the streamed sample std equals the uncertainty module's."""

from __future__ import annotations

import pytest

from monai_probreg.cli.pipeline import RegistrationOptions
from monai_probreg.utils.errors import InputError


@pytest.mark.parametrize("samples", [-1, 1])
def test_samples_must_allow_a_standard_deviation(samples):
    with pytest.raises(InputError, match="--samples"):
        RegistrationOptions(samples=samples)
