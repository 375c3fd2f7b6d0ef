"""The MONAI model zoo's view of the network: one 2-channel input, the displacement out.

MONAI's bundle checks call the network with ONE tensor built from ``metadata.json``'s ``network_data_format``:
``verify_net_in_out`` runs ``net(torch.rand(1, 2, *S))`` and checks ``output.shape[1]`` (3, the ``pred``
output's channels) and ``output.dtype``; ``ckpt_export`` loads a ``state_dict`` into the network and compiles it
with ``torch.jit.script``. :class:`~monai_probreg.ProbRegNet` takes ``forward(moving, fixed)`` and returns a
:class:`~monai_probreg.RegistrationOutput` named tuple, so it cannot answer either check as it is.

:class:`PairInputNet` is a :class:`~monai_probreg.ProbRegNet` (same constructor, same parameters, same
``state_dict`` keys: the bundle's ``models/*.pt`` load into it unchanged) whose ``forward`` takes the pair on the
channel axis and returns only the displacement. The bundle declares it as ``zoo_network_def``, next to the
``network_def`` the workflows use.
"""

from __future__ import annotations

from torch import Tensor

from monai_probreg.networks.probreg_net import ProbRegNet
from monai_probreg.utils.tensors import shape_str

__all__ = ["PairInputNet"]


class PairInputNet(ProbRegNet):
    """:class:`~monai_probreg.ProbRegNet` with the model zoo's call: ``forward(image) -> displacement``.

    ``image`` (B, 2 C, *S): moving on channels ``[0, C)``, fixed on ``[C, 2 C)`` (``metadata.json``'s
    ``channel_def``: 0 moving, 1 fixed; C = ``in_channels``, 1 for the bundle). Returns the ``pred`` output,
    the displacement (B, spatial_dims, *S) in voxels of the input grid, channel k along tensor axis 2 + k, pull
    back ``warped[x] = moving[x + displacement[x]]``: exactly ``ProbRegNet.forward(moving, fixed).displacement``
    (posterior mean in eval mode, a sample in train mode). The warped image is not computed; warp with
    :func:`~monai_probreg.blocks.warp.warp_image` if needed. Every other method (``posterior``, ``sample``, ...) is
    ProbRegNet's. Compiles with ``torch.jit.script`` (bundle ``ckpt_export --net_id zoo_network_def``).

    Args: those of :class:`~monai_probreg.ProbRegNet`.
    """

    def forward(self, image: Tensor) -> Tensor:  # type: ignore[override]
        if image.ndim != self.spatial_dims + 2 or image.shape[1] < 2 or image.shape[1] % 2 != 0:
            raise ValueError(
                "image must be (B, 2 C, *S) with moving and fixed on the channel axis and "
                + str(self.spatial_dims)
                + " spatial dims; got shape "
                + shape_str(image.shape)
            )
        channels = image.shape[1] // 2
        moving, fixed = image[:, :channels], image[:, channels:]
        posterior = self.posterior(moving, fixed)
        velocity = self.sampler(posterior.mean, posterior.log_var)
        return self.velocity_to_displacement(velocity, moving.shape[2:])
