"""A noise estimated from the residuals grows with the misfit, so it never excuses one: the σ
guards judge such data by their absolute floor (as data with no spreads at all)."""

from calib.robot.controller import MIN_SIGMA_GUARD_MM, do_not_enter_reasons


def _doc(sigma: float, noise: float, estimated: bool) -> dict:
    doc = {"diagnostics": {"error_budget": {"tracker": {"sigma_mm": sigma, "noise_mm": noise, "n_rows": 100}}}}
    if estimated:
        doc["noise_estimate"] = {"how": "estimated from the data", "sensors": {"tracker": {"position_mm": noise}}}
    return doc


def test_a_large_sigma_is_refused_even_when_the_estimated_noise_is_as_large():
    sigma = 3 * MIN_SIGMA_GUARD_MM
    assert do_not_enter_reasons(_doc(sigma, 0.9 * sigma, estimated=True))  # the estimate follows the misfit
    assert not do_not_enter_reasons(_doc(sigma, 0.9 * sigma, estimated=False))  # a stated noise that large explains it
    assert not do_not_enter_reasons(_doc(0.5 * MIN_SIGMA_GUARD_MM, 0.4 * MIN_SIGMA_GUARD_MM, estimated=True))
