r"""Feature extractors ("trunks") for the observation encoders of the deep state-space models.

An encoder in this book is ``trunk -> heads``: the trunk turns a raw observation :math:`o_t`
into a feature vector, and the heads of :class:`pgm_wm.rkn.ObservationEncoder` turn the
features into the latent observation :math:`w_t` and its variance :math:`\sigma^{obs}_t`
(Eq. rkn-encoder). Vector observations use an MLP trunk (the default of
``ObservationEncoder``); images use the small convolutional trunk below.
"""

from __future__ import annotations

from typing import Sequence

from torch import Tensor, nn

from ._checks import check_last_dims

__all__ = ["ConvTrunk"]


class ConvTrunk(nn.Module):
    """A small convolutional feature extractor for flattened single-channel images.

    ``(..., H*W) -> (..., feature_dim)``: reshape to ``(N, 1, H, W)``, subtract ``pixel_mean``, then for every entry of
    ``channels`` a ``kernel_size`` convolution with stride 2 (padding keeps ``ceil(size / 2)``)
    and ReLU, then flatten, a linear layer to ``feature_dim`` and ReLU. Any number of leading
    (batch, time) dimensions is accepted; frames are processed independently.

    Args:
        image_shape: ``(H, W)`` of one frame.
        channels: output channels of each convolution, e.g. ``(8, 16)``.
        feature_dim: size of the output feature vector.
        kernel_size: odd kernel size of every convolution.
        pixel_mean: subtracted from every pixel first (0.5 centres intensities in ``[0, 1]``,
            which makes the first layer learn noticeably faster).
    """

    def __init__(
        self,
        image_shape: Sequence[int],
        channels: Sequence[int] = (8, 16),
        feature_dim: int = 32,
        kernel_size: int = 3,
        pixel_mean: float = 0.5,
    ) -> None:
        super().__init__()
        if len(image_shape) != 2 or min(image_shape) <= 0:
            raise ValueError(f"image_shape: expected (H, W) with positive sizes, got {tuple(image_shape)}")
        if len(channels) == 0 or min(channels) <= 0:
            raise ValueError(f"channels: expected a non-empty list of positive sizes, got {tuple(channels)}")
        if feature_dim <= 0:
            raise ValueError(f"feature_dim: must be positive, got {feature_dim}")
        if kernel_size <= 0 or kernel_size % 2 == 0:
            raise ValueError(f"kernel_size: must be a positive odd number, got {kernel_size}")
        self.image_shape = (int(image_shape[0]), int(image_shape[1]))
        self.obs_dim = self.image_shape[0] * self.image_shape[1]
        self.feature_dim = int(feature_dim)
        self.pixel_mean = float(pixel_mean)
        layers: list[nn.Module] = []
        c_in, (h, w) = 1, self.image_shape
        for c in channels:
            layers += [nn.Conv2d(c_in, c, kernel_size, stride=2, padding=kernel_size // 2), nn.ReLU()]
            c_in, h, w = c, (h + 1) // 2, (w + 1) // 2
        self.convs = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(c_in * h * w, self.feature_dim), nn.ReLU())

    def forward(self, obs: Tensor) -> Tensor:
        """``obs: (..., H*W)`` -> features ``(..., feature_dim)``."""
        check_last_dims("obs", obs, (self.obs_dim,))
        lead = obs.shape[:-1]
        x = obs.reshape(-1, 1, *self.image_shape) - self.pixel_mean
        return self.head(self.convs(x)).reshape(*lead, self.feature_dim)
