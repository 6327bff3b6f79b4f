"""The energy estimator's logsumexp (models/base.py `logsumexp_classes`): the same floats as torch.logsumexp, also
where most differences to the maximum are far below exp's normal range (a peaked model, whose exp there would
be subnormal), for infinite and NaN logits, in both memory layouts a model hands over."""
from __future__ import annotations

import math

import torch

from pairedgta.models.base import SUBNORMAL_EXP, logsumexp_classes


def logits(scale: float, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(3, 19, 33, 47, generator=g) * scale


def test_the_same_floats_as_torch_for_flat_and_peaked_logits_in_either_layout():
    for scale in (0.5, 5.0, 60.0, 400.0):  # 60 and more: most differences below SUBNORMAL_EXP
        for z in (logits(scale), logits(scale).contiguous(memory_format=torch.channels_last)):
            d = z - z.amax(dim=1, keepdim=True)
            if scale >= 60:
                assert (d < SUBNORMAL_EXP).float().mean() > 0.5  # the case the clamp is for is there
            assert torch.equal(logsumexp_classes(z), torch.logsumexp(z, dim=1)), scale


def test_infinite_and_nan_logits_as_torch():
    z = logits(3.0)
    z[0, 4, 0, 0] = math.inf
    z[1, :, 2, 3] = -math.inf
    z[2, 7, 5, 5] = math.nan
    ours, torchs = logsumexp_classes(z), torch.logsumexp(z, dim=1)
    assert torch.equal(ours.isnan(), torchs.isnan())
    ok = ~torchs.isnan()
    assert torch.equal(ours[ok], torchs[ok])
    assert ours[0, 0, 0] == math.inf and ours[1, 2, 3] == -math.inf and math.isnan(ours[2, 5, 5])
