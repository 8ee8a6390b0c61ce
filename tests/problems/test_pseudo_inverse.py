"""The pseudo-inverse of a normal matrix (problems/uncertainty.py: psd_pinv), which the loop's linear
cross-validation takes thousands of times per candidate: by Cholesky where the condition number
allows it, by eigendecomposition elsewhere, the pseudo-inverse either way."""
from __future__ import annotations

import torch

from torchcal.problems.uncertainty import psd_pinv

D = torch.float64


def test_psd_pinv_is_the_pseudo_inverse():
    """The Cholesky shortcut where the condition number allows it, the eigendecomposition elsewhere:
    the pseudo-inverse either way (well conditioned, singular, barely above the cut)."""
    g = torch.Generator().manual_seed(9)
    B = torch.randn(6, 30, 12, generator=g, dtype=D)
    G = B.mT @ B  # well conditioned
    G[1] = G[1] * 0
    r = torch.randn(12, 7, generator=g, dtype=D)
    G[2] = r @ r.T  # rank 7: singular
    Q, _ = torch.linalg.qr(torch.randn(12, 12, generator=g, dtype=D))
    G[3] = Q @ torch.diag(torch.logspace(0, -11, 12, dtype=D)) @ Q.T  # above the cut, beyond the shortcut
    G[4] = Q @ torch.diag(torch.logspace(0, -14, 12, dtype=D)) @ Q.T  # some below the cut
    ref = torch.linalg.pinv(G, rtol=1e-12, hermitian=True)
    H = psd_pinv(G)
    for b in range(6):
        scale = float(ref[b].abs().max()) or 1.0
        assert float((H[b] - ref[b]).abs().max()) <= 1e-6 * scale, b
    torch.testing.assert_close(H[0], torch.linalg.inv(G[0]), rtol=1e-9, atol=1e-12)
    assert float(H[1].abs().max()) == 0.0
