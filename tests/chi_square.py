"""The one chi-square goodness-of-fit helper of the sampler tests (PBR: BRDF, environment map,
integrator): histogram counts against the expected counts of the sampled density."""

from __future__ import annotations

import numpy as np
from scipy import stats


def chi_square_pvalue(observed, expected, *, min_expected: float = 5.0, rtol: float = 1e-9) -> float:
    """p-value of Pearson's chi-square test of ``observed`` counts against ``expected`` counts.

    Bins expected to hold fewer than ``min_expected`` samples are pooled into one tail bin, so the
    chi-square approximation holds; a tail that expects nothing is dropped with its counts (e.g.
    below-horizon samples of a density that is zero there). The totals must agree to ``rtol``
    (a sample binned nowhere, or a density that does not integrate to one, fails here); the
    expected counts are then scaled to the observed total of the bins kept."""
    observed = np.asarray(observed, np.float64).ravel()
    expected = np.asarray(expected, np.float64).ravel()
    assert observed.shape == expected.shape
    assert np.isclose(observed.sum(), expected.sum(), rtol=rtol), (observed.sum(), expected.sum())
    small = expected < min_expected
    obs = np.append(observed[~small], observed[small].sum())
    exp = np.append(expected[~small], expected[small].sum())
    keep = exp > 0
    obs, exp = obs[keep], exp[keep]
    return float(stats.chisquare(obs, exp * obs.sum() / exp.sum()).pvalue)
