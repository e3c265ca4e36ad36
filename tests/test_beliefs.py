"""The belief protocol (pgm_wm.beliefs), tested against the dense form as the oracle."""

from __future__ import annotations

import pytest
import torch

from pgm_wm.beliefs import DiagGaussian, FactorizedBelief, Gaussian

D = torch.float64


def make(kind: str, gen: torch.Generator, batch=(3, 2), m: int = 2):
    rnd = lambda *s: torch.rand(*s, generator=gen, dtype=D)  # noqa: E731
    if kind == "diag":
        return DiagGaussian(torch.randn(*batch, m, generator=gen, dtype=D), 0.1 + rnd(*batch, m))
    if kind == "factorized":
        su, sl = 0.1 + rnd(*batch, m), 0.1 + rnd(*batch, m)
        return FactorizedBelief(torch.randn(*batch, 2 * m, generator=gen, dtype=D), su, sl,
                                0.9 * (2 * rnd(*batch, m) - 1) * (su * sl).sqrt())
    L = torch.randn(*batch, m, m, generator=gen, dtype=D)
    return Gaussian(torch.randn(*batch, m, generator=gen, dtype=D), L @ L.transpose(-1, -2) + 0.1 * torch.eye(m, dtype=D))


KINDS = ["dense", "diag", "factorized"]


def same(a: Gaussian, b: Gaussian) -> None:
    torch.testing.assert_close(a.mean, b.mean, rtol=0, atol=0)
    torch.testing.assert_close(a.cov, b.cov, rtol=0, atol=0)


@pytest.mark.parametrize("kind", KINDS)
def test_protocol_agrees_with_the_dense_form(kind):
    gen = torch.Generator().manual_seed(0)
    a, b = make(kind, gen), make(kind, gen)
    da, db = a.to_dense(), b.to_dense()
    # marginal variances are the diagonal of the dense covariance
    torch.testing.assert_close(a.var, torch.diagonal(da.cov, dim1=-2, dim2=-1), rtol=0, atol=0)
    # + : independent sum, means and covariances add
    same((a + b).to_dense(), Gaussian(da.mean + db.mean, da.cov + db.cov))
    # indexing the batch
    same(a[1].to_dense(), Gaussian(da.mean[1], da.cov[1]))
    same(a[:, 0].to_dense(), Gaussian(da.mean[:, 0], da.cov[:, 0]))
    # where
    keep = torch.tensor([[True, False], [False, False], [True, True]])
    want = Gaussian(torch.where(keep[..., None], da.mean, db.mean), torch.where(keep[..., None, None], da.cov, db.cov))
    same(a.where(keep, b).to_dense(), want)
    # stack (default: a new axis before the event axis), cat, at
    st = type(a).stack([a, b])
    same(st.to_dense(), Gaussian(torch.stack([da.mean, db.mean], -2), torch.stack([da.cov, db.cov], -3)))
    same(st.at(1).to_dense(), db)
    st0 = type(a).stack([a, b], dim=0)
    same(st0[0].to_dense(), da)
    ct = type(a).cat([a, b], dim=0)
    same(ct.to_dense(), Gaussian(torch.cat([da.mean, db.mean], 0), torch.cat([da.cov, db.cov], 0)))
    # map / detach / to
    same(a.map(lambda x: 2.0 * x).to_dense(), Gaussian(2.0 * da.mean, 2.0 * da.cov))
    req = a.map(lambda x: x.clone().requires_grad_(True))
    assert not any(t.requires_grad for t in req.detach()._tensors())
    assert all(t.dtype == torch.float32 for t in a.to(torch.float32)._tensors())


def test_sums_with_another_form_are_rejected_and_stack_needs_beliefs():
    gen = torch.Generator().manual_seed(1)
    with pytest.raises(TypeError):
        make("diag", gen) + make("factorized", gen)
    with pytest.raises(ValueError, match="^beliefs"):
        DiagGaussian.stack([])
    with pytest.raises(ValueError, match="^other"):
        make("diag", gen).where(torch.ones(3, 2, dtype=torch.bool), make("factorized", gen))


def test_diag_gaussian_checks_and_unpacks():
    with pytest.raises(ValueError, match="^var"):
        DiagGaussian(torch.zeros(3), torch.ones(2))
    with pytest.raises(ValueError, match="^belief.var"):
        DiagGaussian(torch.zeros(3), torch.tensor([1.0, float("nan"), 1.0])).validate()
    with pytest.raises(ValueError, match="^belief.mean"):
        DiagGaussian(torch.tensor([0.0, float("inf")]), torch.ones(2)).validate()
    mean, var = DiagGaussian(torch.zeros(3), torch.ones(3))
    assert torch.equal(var, torch.ones(3))
    s = DiagGaussian.standard((2,), 3, dtype=D)
    assert torch.equal(s.to_dense().cov, torch.eye(3, dtype=D).expand(2, 3, 3))


def test_factorized_upper_marginal_and_known_point_mass():
    gen = torch.Generator().manual_seed(2)
    f = make("factorized", gen)
    up = f.upper.to_dense()
    same(up, Gaussian(f.to_dense().mean[..., :2], f.to_dense().cov[..., :2, :2]))
    k = FactorizedBelief.known(torch.ones(4, dtype=D))
    assert torch.equal(k.to_dense().cov, torch.zeros(4, 4, dtype=D))


def test_gaussian_importable_from_the_old_paths():
    from pgm_wm.factorized import FactorizedBelief as F2
    from pgm_wm.gaussian import Gaussian as G2

    assert G2 is Gaussian and F2 is FactorizedBelief


def test_gaussian_stack_broadcasts_a_shared_covariance():
    shared = Gaussian(torch.zeros(3, 2, dtype=D), torch.eye(2, dtype=D))
    other = Gaussian(torch.ones(3, 2, dtype=D), 2.0 * torch.eye(2, dtype=D).expand(3, 2, 2))
    st = Gaussian.stack([shared, other])
    assert st.mean.shape == (3, 2, 2) and st.cov.shape == (3, 2, 2, 2)
    same(st.at(0), Gaussian(torch.zeros(3, 2, dtype=D), torch.eye(2, dtype=D).expand(3, 2, 2)))
