"""Tests for pgm_wm.testing, the shared oracles: the random objects satisfy what they promise."""

from __future__ import annotations

import pytest
import torch

from pgm_wm.testing import block_matrix, random_factorized_belief, random_gaussian, random_spd


def test_random_spd_and_gaussian():
    g = torch.Generator().manual_seed(0)
    S = random_spd(5, (3, 2), g, min_eig=0.2)
    assert S.shape == (3, 2, 5, 5) and S.dtype == torch.float64
    torch.testing.assert_close(S, S.transpose(-1, -2), rtol=0, atol=0)
    assert float(torch.linalg.eigvalsh(S).min()) >= 0.2 - 1e-12
    G = random_gaussian(4, 7, torch.Generator().manual_seed(1), torch.float32)
    assert G.mean.shape == (7, 4) and G.cov.dtype == torch.float32
    assert torch.equal(random_spd(3, 2, torch.Generator().manual_seed(5)), random_spd(3, 2, torch.Generator().manual_seed(5)))
    with pytest.raises(ValueError, match="min_eig"):
        random_spd(3, min_eig=0.0)


def test_random_factorized_belief_is_a_valid_covariance_with_bounded_correlation():
    b = random_factorized_belief((50,), 4, torch.Generator().manual_seed(2), max_corr=0.5)
    assert b.mean.shape == (50, 8)
    assert bool(((b.var_upper >= 0.5) & (b.var_upper <= 1.5) & (b.var_lower >= 0.5)).all())
    rho = b.cov_side / (b.var_upper * b.var_lower).sqrt()
    assert float(rho.abs().max()) <= 0.5 and float(rho.abs().max()) > 0.3
    assert float(torch.linalg.eigvalsh(b.to_dense().cov).min()) > 0
    with pytest.raises(ValueError, match="max_corr"):
        random_factorized_belief(2, 3, max_corr=1.0)


def test_block_matrix_places_the_blocks():
    blocks = [torch.full((2, 2), float(k)) for k in range(4)]
    M = block_matrix(*blocks)
    assert M.shape == (4, 4)
    assert float(M[0, 0]) == 0 and float(M[0, 3]) == 1 and float(M[3, 0]) == 2 and float(M[3, 3]) == 3
    with pytest.raises(ValueError, match="b11"):
        block_matrix(blocks[0], blocks[1], blocks[2], torch.zeros(3, 3))
