"""Zero-offset fitting: from a dataset and a robot model to offsets with honest uncertainty.

``fit_offsets`` runs the whole method:

1. an initial registration per sensor (least squares on the nominal model, or the paper's three
   points);
2. identifiability at the start: exactly undetermined combinations (e.g. the first joint's
   offset against a rotation of the registration about the base z axis) are resolved by fixing
   one parameter at its nominal value, with the reason recorded;
3. the posterior mode (Gauss–Newton/Levenberg–Marquardt; IRLS for Student-t errors);
4. samples: the fast exact independence sampler (default) or the paper's Metropolis;
5. identifiability again at the estimate, and offsets whose posterior spread is too wide to be
   useful are reported as undetermined, not given a number to type in.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from calib.measure.dataset import Dataset, DatasetError
from calib.plan.identifiability import Identifiability, analyse
from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel
from calib.fit.posterior import REG_NAMES, OffsetPosterior, ParamMask
from calib.fit.registration import register_least_squares, register_three_points
from calib.fit.sampling import Chains, effective_sample_size, independence_mh, paper_metropolis, split_rhat


@dataclass(frozen=True)
class FitOptions:
    """What to fit and how.

    joints: 1-based axis numbers to fit (None: all); others stay at nominal.
    fix_registration: keep each sensor's registration at ``registration`` (or the initial one).
    registration: known base2sensor (4, 4) per sensor, e.g. from a base-mounted reference.
    error: "gaussian" (the paper's) or "student" (heavy-tailed, ν = ``nu``).
    initial_registration: "least-squares" or "three-point" (the paper's).
    max_std_deg: an offset whose posterior std exceeds this is reported as undetermined.
    paper_start: where the paper's sampler starts — "zero" (the paper: all corrections 0,
    σ = 1 mm) or "mode" (the posterior mode, so a short run is not all burn-in).
    link_tolerance: (mm, deg) prior standard deviations of the link parameters d, a and α, β
    (β in mdh models) that the fast method marginalises, so the offsets' intervals include what
    link errors of that size could bias (see ``calib.fit.posterior``); None gives the paper's model.
    The paper's method always uses the paper's model.
    compliance: also fit one joint compliance per axis (rad/(N·m), gravity sag; the robot model
    must give link masses): ``calib.fit.posterior``. Fast method only.
    tool_prior_mm: prior standard deviation (mm, per coordinate) of each measured marker's position
    in the flange frame about the model's value: the markers are fitted by every method, with their
    own posterior (``FitResult.tool``). 0 takes the model's positions as exact (the paper's model).
    linearise_links: the fast sampler predicts the markers by an expansion about the mode —
    second order in the offsets, first in the link parameters (``OffsetPosterior.expand``,
    ``calib.fit.offset_expansion``): the same posterior to ~1e-4 mm, each batch checked against the
    chain walk, many times cheaper. False walks the whole chain for every draw (the reference).
    """

    method: str = "fast"
    joints: tuple[int, ...] | None = None
    fix_registration: bool = False
    registration: dict[str, np.ndarray] | None = None
    error: str = "gaussian"
    nu: float = 4.0
    initial_registration: str = "least-squares"
    seed: int = 0
    n_chains: int = 4
    n_draws: int = 1000
    paper_samples: int = 200_000
    paper_burn_in: int = 175_000
    max_std_deg: float = 1.0
    paper_start: str = "zero"
    link_tolerance: tuple[float, float] | None = (0.2, 0.02)
    compliance: bool = False
    linearise_links: bool = True
    tool_prior_mm: float = 10.0


@dataclass
class FitResult:
    """Everything a report needs. Angles in rad unless a name says deg."""

    model: RobotModel
    posterior: OffsetPosterior
    chains: Chains
    mode: np.ndarray  # (dim + S,) free θ then log σ per sensor
    offsets_rad: np.ndarray  # (n,) posterior mean (0 where fixed)
    offsets_std_rad: np.ndarray  # (n,) NaN where fixed or undetermined
    offsets_ci95_rad: np.ndarray  # (n, 2)
    offset_status: list[str]  # per joint: "fitted", "fixed: …", "undetermined: …"
    base2sensor: dict[str, np.ndarray]  # final registration per sensor
    base2sensor0: dict[str, np.ndarray]
    sigma_mm: dict[str, tuple[float, float]]  # mean, std per sensor
    identifiability_start: Identifiability
    identifiability: Identifiability
    diagnostics: dict = field(default_factory=dict)
    #: Per fitted marker: {"marker", "nominal_mm", "value_mm", "std_mm", "ci95_mm", "prior_mm"} in the
    #: flange frame (``tool_summary``); empty when the tool was taken as exact.
    tool: list[dict] = field(default_factory=list)

    @property
    def fitted_markers_mm(self) -> dict[str, np.ndarray]:
        """Marker name → (3,) fitted position in the flange frame, mm (only the fitted markers)."""
        return {t["marker"]: np.array(t["value_mm"]) for t in self.tool}

    @property
    def full_samples(self) -> np.ndarray:
        """Posterior draws as full vectors (n_draws_total, n + 6·S)."""
        dim = self.posterior.dim
        return self.posterior.full_vector(self.chains.flat[:, :dim])

    @property
    def offset_samples_rad(self) -> np.ndarray:
        return self.full_samples[:, : self.model.n_joints]

    def identifiable(self) -> np.ndarray:
        return np.array([s == "fitted" for s in self.offset_status])

    @property
    def applied_offsets_rad(self) -> np.ndarray:
        """(n,) the offsets to enter: the estimate where identifiable, 0 (unchanged) elsewhere."""
        return np.where(self.identifiable(), self.offsets_rad, 0.0)

    @property
    def applied_sigma_mm(self) -> float:
        """Per-axis RMS error (mm) of the robot as it will be corrected: the applied offsets with
        the nominal link parameters, registered per sensor by least squares. This — not the
        posterior σ, which with the link prior also explains link errors the controller will not
        be told about — is the isotropic error for the theoretical metrics (Sec. V-C)."""
        from calib.fit.metrics import absolute_errors, predicted_base

        data = self.posterior.data
        err = absolute_errors(data, predicted_base(self.posterior.chain, data, self.applied_offsets_rad,
                                                   markers_mm=self.fitted_markers_mm))
        return float(np.sqrt(np.mean(err**2) / 3.0))

    @property
    def pooled_sigma_mm(self) -> float:
        """One isotropic error scale for all sensors: RMS of σ_s weighted by their rows, mm."""
        counts = self.posterior.rows_per_sensor
        sig = np.array([self.sigma_mm[s][0] for s in self.posterior.sensors])
        return float(np.sqrt(np.sum(counts * sig**2) / np.sum(counts)))


#: Posterior methods of ``fit_offsets``: the independence sampler, the paper's Metropolis, and the
#: Laplace approximation checked by Pareto-smoothed importance sampling (``_sample_laplace``).
METHODS = ("fast", "paper", "laplace")

#: Fewest measurements a sensor's registration needs (three points that are not collinear).
MIN_ROWS_PER_SENSOR = 3


def min_measurements(n_free: int) -> int:
    """Fewest measurements (rows, 3 coordinates each) ``fit_offsets`` accepts for ``n_free``
    free parameters: two coordinates per parameter."""
    return math.ceil(2 * n_free / 3)


def min_configurations(n_fitted_joints: int, markers_per_sensor: Sequence[int], *,
                       fix_registration: bool = False) -> int:
    """Fewest configurations a measurement plan needs for ``fit_offsets`` to give a result, before
    anything is measured: ``n_fitted_joints`` offsets plus, per sensor, its registration (6,
    unless fixed) and its σ; each configuration gives one row per marker per sensor
    (``markers_per_sensor``). A lower bound: compliances and lost targets need more."""
    if not markers_per_sensor or min(markers_per_sensor) < 1:
        raise ValueError(f"every sensor measures at least one marker, given {list(markers_per_sensor)}")
    n_free = n_fitted_joints + len(markers_per_sensor) * ((0 if fix_registration else 6) + 1)
    by_parameters = math.ceil(min_measurements(n_free) / sum(markers_per_sensor))
    by_registration = max(math.ceil(MIN_ROWS_PER_SENSOR / m) for m in markers_per_sensor)
    return max(by_parameters, by_registration)


def initial_registrations(chain: Chain, data: Dataset, method: str, seed: int) -> dict[str, np.ndarray]:
    """base2sensor (4, 4) per sensor from the nominal model."""
    pred = chain.marker_positions(data.q_rad)
    idx = np.array([chain.marker_names.index(m) for m in data.marker])
    p_base = pred[np.arange(len(data)), idx]
    out = {}
    rng = np.random.default_rng(seed)
    for s in data.sensors:
        rows = np.flatnonzero(data.sensor == s)
        if rows.size < MIN_ROWS_PER_SENSOR:
            raise DatasetError(f"sensor {s!r} has {rows.size} measurements; a registration needs at least "
                               f"{MIN_ROWS_PER_SENSOR}")
        if method == "least-squares":
            out[s] = register_least_squares(p_base[rows], data.xyz_mm[rows]).base2sensor
        elif method == "three-point":
            # The paper samples three non-collinear points; we take the widest of a few draws.
            best, best_area = None, 0.0
            for _ in range(64):
                tri = rng.choice(rows, size=3, replace=False)
                a, b, c = p_base[tri]
                area = 0.5 * np.linalg.norm(np.cross(b - a, c - a))
                if area > best_area:
                    best, best_area = tri, area
            out[s] = register_three_points(p_base[best], data.xyz_mm[best]).base2sensor
        else:
            raise ValueError(f"initial_registration {method!r} unknown; use 'least-squares' or 'three-point'")
    return out


def _scale(post: OffsetPosterior, lever_mm: float) -> np.ndarray:
    """Per free parameter: mm per unit (lever arm for angles, 1 for translations, lever arm ×
    rms torque for compliances in µrad/(N·m))."""
    out = []
    for k, name in zip(post.free, post.free_names):
        kind = name.rsplit(".", 1)[1]
        if kind == "compliance":
            i = k - (post.n_full - post.C)
            out.append(lever_mm * 1e-6 * float(np.sqrt(np.mean(post.torques[:, i] ** 2))) or 1.0)
        else:
            out.append(1.0 if kind in ("x", "y", "z", "d", "a") else lever_mm)
    return np.array(out)


def _tool_prior(chain: Chain, data: Dataset, options: FitOptions) -> dict[int, float]:
    """Chain parameter index → prior sd (mm) of the coordinates of every marker the data measure."""
    sd = options.tool_prior_mm
    if not (math.isfinite(sd) and 0 <= sd <= 100):
        raise ValueError(f"tool_prior_mm must lie in 0…100 mm (0: the model's marker positions are exact), given {sd}")
    if sd == 0:
        return {}
    start = chain.marker_slice().start
    measured = set(data.marker.tolist())
    return {start + 3 * m + c: float(sd) for m, name in enumerate(chain.marker_names) if name in measured for c in range(3)}


def _link_prior(chain: Chain, options: FitOptions) -> dict[int, float]:
    """Chain parameter index → prior sd (mm or rad) of the link parameters to marginalise."""
    if options.link_tolerance is None:
        return {}
    length_mm, angle_deg = options.link_tolerance
    if not (length_mm > 0 and angle_deg > 0):
        raise ValueError(f"link_tolerance must be positive (mm, deg), given {options.link_tolerance}")
    kinds = ["d", "a", "alpha"] + (["beta"] if chain.model.convention == "mdh" else [])
    prior = {}
    for kind in kinds:
        sd = length_mm if kind in ("d", "a") else math.radians(angle_deg)
        for i in chain.index(kind):
            prior[int(i)] = sd
    return prior


def _flat_prior_analysis(post: OffsetPosterior, theta: np.ndarray, lever_mm: float) -> Identifiability:
    """Identifiability of the parameters with flat priors (offsets, registration): the link
    parameters' priors make their own directions proper, so they do not count here."""
    link_pos, _ = post.link_free()
    keep = np.setdiff1d(np.arange(post.dim), link_pos)
    j = post.jacobian(theta)[:, keep]
    return analyse(j, [post.free_names[k] for k in keep], _scale(post, lever_mm)[keep])


def _resolve_null_space(post_factory, mask: ParamMask, lever_mm: float) -> tuple[ParamMask, Identifiability]:
    """Fix parameters until the Jacobian at the start has full rank; record why."""
    first = None
    for _ in range(64):
        post = post_factory(mask)
        ident = _flat_prior_analysis(post, np.zeros(post.dim), lever_mm)
        first = first or ident
        if not ident.deficient:
            return mask, first
        combo = ident.null_space[0]
        offsets = {k: v for k, v in combo.loadings.items() if k.endswith(".offset")}
        pick_from = offsets or combo.loadings
        name = max(pick_from, key=lambda k: abs(pick_from[k]))
        others = [k for k in combo.loadings if k != name]
        how = "exactly" if combo.exact else "almost exactly"
        reason = (
            f"not determined by this data: it moves the markers {how} like "
            f"{', '.join(others) if others else 'nothing'} (combination {combo.describe()}: {combo.explain()}); "
            f"kept at its nominal value"
        )
        if name == f"{post.chain.model.axis_names[0]}.offset" and mask.registration.any():
            reason += "; the first axis's offset needs a base-fixed reference (fix the registration) to be measured"
        mask = mask.fix(post.names.index(name), reason, post.names)
    raise RuntimeError("could not resolve the undetermined parameters")  # pragma: no cover


def _resolve_rigid_links(post_factory, mask: ParamMask) -> ParamMask:
    """Fix the link parameters that only move the whole arm rigidly, or only the tool on the
    flange: whose markers' motion the registrations reproduce exactly (the first link's tilt and
    shifts ahead of joint 1 — β₁, d₁ in mdh, d₁ in dh), or the fitted markers' coordinates do (the
    last link's d in mdh; its d, a and α, which follow the last joint, in dh). The registration
    (flat prior) or the tool (its prior 10× wider) takes them — exactly, to every order, since
    a rigid move of the base or of the markers is another registration or another set of
    marker positions — so marginalising them changes no offset's posterior, while their priors
    alone would hold long ridges, curved where they are turns (a 0.1° tilt is a 4 mm shift at a
    tracker 2 m away), that neither the Laplace approximation nor a sampler follows. Kept at
    their nominal values, with the reason."""
    post = post_factory(mask)
    start = post.n + 6 * post.S
    link_pos, _ = post.link_free()
    link_pos = [k for k in link_pos if not post.is_tool[post.free[k] - start]]
    if not link_pos:
        return mask
    j = post.jacobian(np.zeros(post.dim))
    reg = [k for k, i in enumerate(post.free) if post.n <= i < start]
    tool = [k for k, i in enumerate(post.free) if i >= start and i < start + post.L and post.is_tool[i - start]]
    spans = [(cols, why) for cols, why in (
        (reg, "moves the whole arm rigidly, as the registration does: the registration takes it"),
        (tool, "moves the markers rigidly on the flange, as the fitted tool does: the tool takes it")) if cols]
    for cols, why in spans:
        q, _ = np.linalg.qr(j[:, cols])
        for k in link_pos:
            col = j[:, k]
            norm = np.linalg.norm(col)
            if mask.full[post.free[k]] and norm > 0 and np.linalg.norm(col - q @ (q.T @ col)) <= 1e-9 * norm:
                coef = np.linalg.lstsq(j[:, cols], col, rcond=None)[0]
                like = [post.free_names[cols[i]] for i in np.flatnonzero(np.abs(coef) > 0.05 * np.abs(coef).max())]
                mask = mask.fix(int(post.free[k]), f"{why} (it moves the markers exactly like {', '.join(like)}); "
                                "kept at its nominal value", post.names)
    return mask


def _resolve_tool(post_factory, mask: ParamMask, lever_mm: float, prior_mm: float) -> ParamMask:
    """Fix the offsets that move the markers exactly like a move of the tool on the flange (the
    last axis's offset against a turn of the tool about that axis): the fitted tool takes that
    motion, so a corrected model stays right for another tool on the same flange. The tool's
    coordinates are never fixed: their prior keeps them proper."""
    for _ in range(16):
        post = post_factory(mask)
        if not post.is_tool.any():
            return mask
        start = post.n + 6 * post.S
        link_pos, _ = post.link_free()
        keep = [k for k in range(post.dim) if k not in set(link_pos.tolist()) or post.is_tool[post.free[k] - start]]
        j = post.jacobian(np.zeros(post.dim))[:, keep]
        ident = analyse(j, [post.free_names[k] for k in keep], _scale(post, lever_mm)[keep])
        tool_names = {post.names[start + i] for i in np.flatnonzero(post.is_tool)}
        for combo in ident.null_space:
            offsets = {k: v for k, v in combo.loadings.items() if k.endswith(".offset") and abs(v) > 1e-3}
            tools = [k for k, v in combo.loadings.items() if k in tool_names and abs(v) > 1e-3]
            if offsets and tools:
                name = max(offsets, key=lambda k: abs(offsets[k]))
                reason = (f"not separable from the tool: it moves the markers {'exactly' if combo.exact else 'almost exactly'} "
                          f"like a move of the tool on the flange ({', '.join(tools)}; combination {combo.describe()}); the tool's position is fitted "
                          f"(prior ±{prior_mm:g} mm) and takes this motion, so the offset is kept at its nominal value — "
                          "with the markers' positions known, give --tool-prior-mm 0 to fit it")
                mask = mask.fix(post.names.index(name), reason, post.names)
                break
        else:
            return mask
    return mask


def _levenberg_marquardt(fun, jac, x0: np.ndarray, *, tol: float = 1e-12, max_iter: int = 200) -> np.ndarray:
    """Minimise |fun(x)|² (fun: (p,) → (m,), jac: its (m, p) Jacobian) from x0 (p,).

    Levenberg–Marquardt with Marquardt's column scaling, each step a least-squares solve of the
    damped system (no normal equations: offsets in rad next to translations in mm square into a
    poor conditioning). Stops when a step changes x by less than ``tol`` relative, or the cost by
    less than ``tol`` relative. Small dense problems only (the mode: tens of parameters)."""
    x = np.asarray(x0, dtype=float).copy()
    f = fun(x)
    cost = float(f @ f)
    lam = 1e-3
    scale = np.zeros(x.size)
    for _ in range(max_iter):
        j = jac(x)
        scale = np.maximum(scale, np.linalg.norm(j, axis=0))
        d = np.where(scale > 0, scale, 1.0)
        while True:
            damped = np.vstack([j, np.diag(math.sqrt(lam) * d)])
            step = np.linalg.lstsq(damped, np.concatenate([-f, np.zeros(x.size)]), rcond=None)[0]
            x_new = x + step
            f_new = fun(x_new)
            cost_new = float(f_new @ f_new)
            if cost_new <= cost:
                break
            lam *= 10.0
            if lam > 1e16:
                return x
        x, f, gain, cost = x_new, f_new, cost - cost_new, cost_new
        lam = max(lam / 10.0, 1e-12)
        if np.linalg.norm(d * step) <= tol * (np.linalg.norm(d * x) + tol) or gain <= tol * cost:
            break
    return x


def _mode(post: OffsetPosterior, error: str, nu: float, tol: float = 1e-12,
          theta0: np.ndarray | None = None, sigma0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Posterior mode: θ (dim,) and log σ (S,); ``tol``: relative step/cost change that ends a solve;
    ``theta0``, ``sigma0`` (S,) mm: where to start (zeros and 1 mm: the nominal model)."""
    s_idx = post.sensor_index
    n_s = post.rows_per_sensor
    theta = np.zeros(post.dim) if theta0 is None else np.asarray(theta0, dtype=float).copy()
    sigma = np.ones(post.S) if sigma0 is None else np.asarray(sigma0, dtype=float).copy()
    weights = np.ones(post.n_rows)
    link_pos, link_sd = post.link_free()
    prior_rows = np.zeros((link_pos.size, post.dim))
    prior_rows[np.arange(link_pos.size), link_pos] = 1.0 / link_sd
    # Alternate: θ by least squares at fixed σ (and Student weights), then σ at fixed θ, until σ
    # settles — with link parameters free σ can fall by two orders of magnitude, which
    # reweights data against the priors.
    for _ in range(40):
        previous = sigma.copy()
        w = np.sqrt(weights / sigma[s_idx] ** 2)[:, None]

        def fun(t, w=w):
            return np.concatenate([(post.residuals(t) * w).ravel(), t[link_pos] / link_sd])

        def jac(t, w=w):
            j = -(post.jacobian(t).reshape(post.n_rows, 3, -1) * w[:, :, None]).reshape(post.n_rows * 3, -1)
            return np.concatenate([j, prior_rows])

        theta = _levenberg_marquardt(fun, jac, theta, tol=tol)
        r2 = np.sum(post.residuals(theta) ** 2, axis=-1)
        if error == "gaussian":
            # Mode of σ in (θ, log σ) coordinates: ∂/∂logσ [−(3n+1) log σ − E/2σ²] = 0.
            sigma = np.sqrt(np.bincount(s_idx, r2, minlength=post.S) / (3 * n_s + 1))
        else:
            weights = (nu + 3) / (nu + r2 / sigma[s_idx] ** 2)
            sigma = np.sqrt(np.bincount(s_idx, weights * r2, minlength=post.S) / (3 * n_s + 1))
        if np.all(np.abs(np.log(sigma / previous)) < max(1e-6, math.sqrt(tol))):
            break
    return theta, np.log(sigma)


#: The smallest eigenvalue of the correlation-scaled curvature, relative to the largest, below which a
#: combination of parameters counts as undetermined (a condition number of 1e10: its variance would be
#: lost in rounding, and the samplers' Cholesky fails).
MIN_CURVATURE_RATIO = 1e-10


def _require_determined(post: OffsetPosterior, h: np.ndarray) -> np.ndarray:
    """Refuse a curvature ``h`` (dim, dim) that is not positive definite: the measured configurations
    leave a combination of parameters free (too few, or too alike, for this model). Returns the
    scale (dim,) that makes ``h``'s diagonal one."""
    scale = np.sqrt(np.maximum(np.diag(h), 1e-300))
    vals, vecs = np.linalg.eigh(h / np.outer(scale, scale))  # correlation-scaled: units drop out
    if vals[0] <= MIN_CURVATURE_RATIO * vals[-1]:
        names = [post.free_names[i] for i in np.argsort(-np.abs(vecs[:, 0]))[:3]]
        raise DatasetError(
            f"the {post.n_rows} measurements do not determine every parameter of this model: "
            f"{', '.join(names)} can move together without changing them; measure more, and more different, "
            "configurations, or fit a smaller model (fewer link terms, no compliance)") from None
    return scale


def _laplace_covariance(post: OffsetPosterior, theta: np.ndarray, log_sigma: np.ndarray) -> np.ndarray:
    """Gauss–Newton covariance of (θ, log σ) at the mode."""
    j = post.jacobian(theta).reshape(post.n_rows, 3, -1)
    w = np.exp(-2 * log_sigma)[post.sensor_index]
    h = np.einsum("kip,k,kiq->pq", j, w, j) + _prior_precision(post)
    scale = _require_determined(post, h)
    cov_t = np.linalg.pinv(h / np.outer(scale, scale)) / np.outer(scale, scale)  # scaled: units do not cut it
    cov = np.zeros((post.dim + post.S,) * 2)
    cov[: post.dim, : post.dim] = 0.5 * (cov_t + cov_t.T)
    cov[post.dim :, post.dim :] = np.diag(1.0 / (2.0 * (3 * post.rows_per_sensor + 1)))
    return cov


def _sample_sigma_marginalised(post: OffsetPosterior, theta: np.ndarray, log_sigma: np.ndarray, options: FitOptions) -> Chains:
    """Exact draws of (θ, log σ) for Gaussian errors with σ integrated out.

    With p(θ, σ) ∝ Π_s σ_s^(−3n_s−2) exp(−E_s(θ)/2σ_s²) · prior(θ), the marginal is
    p(θ) ∝ Π_s E_s(θ)^(−(3n_s+1)/2) · prior(θ), and σ_s | θ has 1/σ_s² ~ Gamma((3n_s+1)/2,
    rate E_s/2). θ is drawn by the independence sampler from the marginal — no funnel between θ
    and σ for the proposal to miss — and each draw's σ exactly from its conditional, using the
    sums of squares already computed for the proposals.
    """
    half_dof = 0.5 * (3 * post.rows_per_sensor + 1)  # (S,)
    link_pos, link_sd = post.link_free()
    sse_of_proposals: list[np.ndarray] = []

    def log_marginal(t: np.ndarray) -> np.ndarray:
        e = post.sse(t)  # (b, S)
        sse_of_proposals.append(e)
        out = -(half_dof * np.log(e)).sum(axis=-1)
        if link_pos.size:
            out = out - 0.5 * np.sum((t[..., link_pos] / link_sd) ** 2, axis=-1)
        return out

    cov = _laplace_covariance(post, theta, log_sigma)[: post.dim, : post.dim]
    draws = independence_mh(log_marginal, theta, cov, n_chains=options.n_chains, n_draws=options.n_draws, seed=options.seed)
    e = np.concatenate(sse_of_proposals)[draws.proposal_index]  # (c, n, S)
    rng = np.random.default_rng(options.seed + 7919)
    u = rng.gamma(half_dof, 2.0 / e)  # 1/σ² draws
    log_s = -0.5 * np.log(u)
    samples = np.concatenate([draws.samples, log_s], axis=-1)
    return Chains(samples, draws.acceptance, draws.seconds, "independence-mh (σ marginalised)", draws.proposal_index)


def _sample_laplace(post: OffsetPosterior, theta: np.ndarray, log_sigma: np.ndarray,
                    options: FitOptions, progress=None) -> tuple[Chains, dict]:
    """Draws of (θ, log σ) by the Laplace Gaussian checked with PSIS, or a random walk in the Laplace-whitened coordinates where k̂ ≥ 0.7
    (``calib.fit.laplace_sampling``). Gaussian errors: the target is θ's marginal with σ integrated
    out (as ``_sample_sigma_marginalised``), each draw's σ drawn from its conditional; Student-t:
    the joint (θ, log σ) posterior. Returns (chains, importance diagnostics)."""
    from calib.fit.laplace_sampling import laplace_importance, random_walk

    link_pos, link_sd = post.link_free()
    cov_full = _laplace_covariance(post, theta, log_sigma)
    # Each proposal's sums of squares (S,), by predictor (exact or not), kept while the importance
    # check runs: the σ of a resampled draw is drawn from them instead of walking the chain again.
    sse_of: dict[bool, dict[bytes, np.ndarray]] | None = {False: {}, True: {}}
    walking_exact = [False]
    if options.error == "gaussian":
        half_dof = 0.5 * (3 * post.rows_per_sensor + 1)

        def target(t: np.ndarray) -> np.ndarray:
            e = post.sse(t)
            if sse_of is not None:
                kept = sse_of[walking_exact[0]]
                for row, e_row in zip(t, e):
                    kept[row.tobytes()] = e_row
            out = -(half_dof * np.log(e)).sum(axis=-1)
            if link_pos.size:
                out = out - 0.5 * np.sum((t[..., link_pos] / link_sd) ** 2, axis=-1)
            return out

        start, cov = theta, cov_full[: post.dim, : post.dim]
    else:
        def target(x: np.ndarray) -> np.ndarray:
            return post.log_posterior(x[..., : post.dim], x[..., post.dim:])

        start, cov = np.concatenate([theta, log_sigma]), cov_full
    exact_target = None
    if post.expanded:
        def exact_target(x: np.ndarray) -> np.ndarray:
            walking_exact[0] = True
            try:
                with post.exact():
                    return target(x)
            finally:
                walking_exact[0] = False

    chains, info = laplace_importance(target, start, cov, n_chains=options.n_chains, n_draws=options.n_draws,
                                      seed=options.seed, exact_target=exact_target, progress=progress)
    del info["mean"], info["covariance"]  # (the random walk whitens by the Laplace covariance and re-whitens itself)
    info["fallback"] = None
    known = sse_of[info["predictor"] == "exact" and exact_target is not None]
    sse_of = None  # (the walk's steps are not kept)
    if chains is None:
        known = {}
        use = exact_target if info["predictor"] == "exact" and exact_target is not None else target
        chains = random_walk(use, start, cov, seed=options.seed, progress=progress)
        info["fallback"] = "random-walk Metropolis"
        info["walk"] = chains.diagnostics
    if options.error == "gaussian":
        rng = np.random.default_rng(options.seed + 7919)
        rows = [known.get(row.tobytes()) for row in chains.flat]
        if all(r is not None for r in rows):
            e = np.array(rows).reshape(-1, post.S)
        else:
            e = np.concatenate([post.sse(b) for b in np.array_split(chains.flat, max(1, chains.flat.shape[0] // 1024))])
        u = rng.gamma(half_dof, 2.0 / e)  # 1/σ² draws, (N, S)
        flat = np.concatenate([chains.flat, -0.5 * np.log(u)], axis=-1)
        chains = Chains(flat.reshape(*chains.samples.shape[:2], -1), chains.acceptance, chains.seconds, chains.method)
    return chains, info


def _prior_precision(post: OffsetPosterior) -> np.ndarray:
    """(dim, dim) precision of the Gaussian link priors (zero elsewhere)."""
    pos, sd = post.link_free()
    p = np.zeros((post.dim, post.dim))
    p[pos, pos] = 1.0 / sd**2
    return p


def sandwich_std(post: OffsetPosterior, theta: np.ndarray, log_sigma: np.ndarray) -> np.ndarray:
    """Model-robust standard deviations of the free θ at the mode, (dim,) internal units.

    The posterior's spread assumes independent isotropic errors (eq. 10). The sandwich
    H⁻¹ B H⁻¹ (H = Σ JᵀWJ, B = Σ_c g_c g_cᵀ with g_c the score of configuration c, rows of one
    configuration pooled) stays right when the error of each configuration is anisotropic or
    differs between configurations — e.g. joint backlash or sag seen through the arm's
    Jacobian. A ratio sandwich / posterior well above 1 says the reported intervals are too
    narrow. Errors correlated across configurations (link-length errors) are not covered.
    """
    j = post.jacobian(theta).reshape(post.n_rows, 3, -1)
    r = post.residuals(theta)
    w = np.exp(-2 * np.asarray(log_sigma))[post.sensor_index]
    h_inv = np.linalg.pinv(np.einsum("kip,k,kiq->pq", j, w, j) + _prior_precision(post))
    score = np.einsum("kip,k,ki->kp", j, w, r)  # (k, dim)
    _, group = np.unique(np.round(post.data.q_rad[post.row_source], 9), axis=0, return_inverse=True)
    pooled = np.zeros((int(group.max()) + 1, score.shape[1]))
    np.add.at(pooled, group.ravel(), score)
    cov = h_inv @ (pooled.T @ pooled) @ h_inv
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))


@dataclass
class ModeFit:
    """The posterior set up for ``data`` and its mode (no sampling): what cross-validation and the
    evidence need. ``theta``: (dim,) free parameters; ``log_sigma``: (S,); ``link_prior``: chain
    index → prior sd (mm or rad) of the link parameters and tool coordinates in the posterior."""

    post: OffsetPosterior
    mask: ParamMask
    theta: np.ndarray
    log_sigma: np.ndarray
    b2s0: dict[str, np.ndarray]
    link_prior: dict[int, float]
    identifiability_start: Identifiability
    lever_mm: float
    #: The chain vector (P,) the compliance sag is taken at (the first mode's arm), or None.
    sag_params: np.ndarray | None = None

    def registrations(self) -> dict[str, np.ndarray]:
        """Sensor name → fitted base2sensor (4, 4): the initial registration with the mode's correction."""
        rot, trans = self.post.corrections(self.post.full_vector(self.theta))
        return {s: _compose(rot[k], trans[k], self.post.b2s0[k]) for k, s in enumerate(self.post.sensors)}

    def predict_residuals(self, data: Dataset) -> np.ndarray:
        """measured − predicted (k, 3) mm for other rows ``data`` with this fit's parameters and its
        own registration (the same sensors; markers the fit did not measure keep the model's place).
        Positions only: attitude rows, where measured, are scored by ``calib.fit.pose_scoring.pose_metrics``."""
        other = OffsetPosterior(self.post.chain, data, self.b2s0, self.mask, error=self.post.error, nu=self.post.nu,
                                link_prior=self.link_prior, compliance=bool(self.post.C), sag_params=self.sag_params,
                                orientation=False)
        return other.position_residuals(self.theta)


def _check_data(model: RobotModel, data: Dataset, options: FitOptions) -> None:
    if data.n_joints != model.n_joints:
        raise DatasetError(f"the dataset has {data.n_joints} joints, the model '{model.name}' has {model.n_joints}")
    if len(data) == 0:
        raise DatasetError("the dataset is empty")
    if not (np.all(np.isfinite(data.q_rad)) and np.all(np.isfinite(data.xyz_mm))):
        raise DatasetError("the dataset contains NaN or infinite values")
    if options.method not in METHODS:
        raise ValueError(f"method {options.method!r} unknown; use one of {', '.join(METHODS)}")
    if options.compliance and options.method == "paper":
        raise ValueError("the compliance model is fitted by the fast and laplace methods only (the paper's model has none)")
    if options.compliance and not model.has_dynamics:
        raise ValueError(f"{model.name}: the compliance model needs link masses and centres of mass in the robot model "
                         "(joints[].mass_kg, com_mm)")


def fit_mode(model: RobotModel, data: Dataset, options: FitOptions = FitOptions(), *, tol: float = 1e-12,
             start: ModeFit | None = None) -> ModeFit:
    """The posterior mode of ``fit_offsets``'s model (same parameters, priors and fixed
    combinations), without sampling: the cheap fit for cross-validation folds. ``tol``: relative
    change that ends the Levenberg–Marquardt solves (1e-8 is ample for prediction).

    ``start``: a mode of this model or a simpler one (fewer free terms) on this data or other data
    of the same cell (the cross-validation folds start from the fit of all the data, the
    candidates on all the data from the one before them): the solves start at its parameters
    (by name; the others at nominal), σ and — on other data — its fitted registration as this
    fit's initial one, so they take a few steps instead of the whole way from the nominal model.
    The mode is the same either way, to ``tol``, wherever the posterior has one mode (the least
    squares of these models do: the staged, multi-start solves of ``calib.fit.identification``
    found no second one on the UR10 and iiwa data)."""
    _check_data(model, data, options)
    chain = Chain(model)
    warm = start is not None and not options.registration and set(start.b2s0) == set(data.sensors)
    same = warm and start.post.data is data  # the start's own data: its initial registration too
    if warm:
        b2s0 = dict(start.b2s0) if same else start.registrations()
    else:
        b2s0 = initial_registrations(chain, data, options.initial_registration, options.seed)
    if options.registration:
        missing = set(data.sensors) - set(options.registration)
        if missing:
            raise ValueError(f"a registration was given for {sorted(options.registration)} but not for {sorted(missing)}")
        b2s0 = {s: np.asarray(options.registration[s], dtype=float) for s in data.sensors}
    n = model.n_joints
    fit_joint = np.ones(n, bool)
    reasons: dict[str, str] = {}
    if options.joints is not None:
        bad = [j for j in options.joints if not 1 <= j <= n]
        if bad:
            raise ValueError(f"joints {bad} do not exist; the model has axes 1…{n}")
        fit_joint = np.isin(np.arange(1, n + 1), options.joints)
        for i in np.flatnonzero(~fit_joint):
            reasons[f"{model.axis_names[i]}.offset"] = "not fitted (excluded by the options)"
    sensors = sorted(b2s0)
    reg_mask = np.full((len(sensors), 6), not options.fix_registration)
    if options.fix_registration:
        for s in sensors:
            for r in REG_NAMES:
                reasons[f"{s}.{r}"] = "registration fixed by the options"
    link_prior = _link_prior(chain, options) if options.method != "paper" else {}
    link_prior.update(_tool_prior(chain, data, options))
    fit_compliance = np.ones(n if options.compliance else 0, bool)
    if options.compliance:
        from calib.robot.gravity import gravity_torques

        rms = np.sqrt(np.mean(gravity_torques(chain, data.q_rad) ** 2, axis=0))
        # An axis that carries a few % of the largest torque sags by microradians: invisible.
        for i in np.flatnonzero(rms < 0.05 * rms.max()):
            fit_compliance[i] = False
            reasons[f"{model.axis_names[i]}.compliance"] = (
                f"gravity turns this axis by only {rms[i] if rms[i] > 1e-9 * rms.max() else 0.0:.1g} N·m (rms) in these "
                "configurations: its sag cannot be seen")
        for i in np.flatnonzero(~fit_joint):
            fit_compliance[i] = False
            reasons[f"{model.axis_names[i]}.compliance"] = "not fitted (its axis is excluded by the options)"
    mask = ParamMask(fit_joint, reg_mask, reasons, np.ones(len(link_prior), bool), fit_compliance)

    # Too few measurements for the free parameters? (Link parameters and the tool carry priors.)
    n_free = int(mask.full.sum()) - len(link_prior) + len(sensors)
    if len(data) < min_measurements(n_free):
        raise DatasetError(
            f"{len(data)} measurements give {3 * len(data)} coordinates for {n_free} free parameters; "
            f"measure at least {min_measurements(n_free)} configurations (more is much better)"
        )

    shared: dict = {}  # what the masks tried below compute alike (``OffsetPosterior``'s ``shared``)

    def factory(m: ParamMask, sag_params: np.ndarray | None = None) -> OffsetPosterior:
        return OffsetPosterior(chain, data, b2s0, m, error=options.error, nu=options.nu, link_prior=link_prior,
                               compliance=options.compliance, sag_params=sag_params,
                               shared=shared if sag_params is None else None)

    p_base = chain.marker_positions(data.q_rad)
    lever = float(np.sqrt(np.mean(np.sum(p_base**2, axis=-1))))
    mask, ident0 = _resolve_null_space(factory, mask, lever)
    mask = _resolve_rigid_links(factory, mask)
    mask = _resolve_tool(factory, mask, lever, options.tool_prior_mm)
    post = factory(mask)
    theta0 = sigma0 = None
    if warm and start.post.sensors == post.sensors:
        full0 = start.post.full_vector(start.theta)
        if not same:
            full0[start.post.n: start.post.n + 6 * start.post.S] = 0.0  # its fitted registration is this fit's initial one
        value = dict(zip(start.post.names, full0))  # by name: the start may be another model (fewer terms)
        theta0, sigma0 = np.array([value.get(name, 0.0) for name in post.free_names]), np.exp(start.log_sigma)
        if options.compliance and start.sag_params is not None:  # the sag at the start's arm: one solve
            post = factory(mask, start.sag_params)
            theta, log_sigma = _mode(post, options.error, options.nu, tol, theta0=theta0, sigma0=sigma0)
            return ModeFit(post, mask, theta, log_sigma, b2s0, link_prior, ident0, lever, start.sag_params)
    theta, log_sigma = _mode(post, options.error, options.nu, tol, theta0=theta0, sigma0=sigma0)
    sag_params = None
    if options.compliance:
        # The sag's torques and levers at the fitted arm (offsets, links, tool), not the nominal one:
        # ``calib.fit.posterior``'s compliance paragraph. One more solve from the first mode; the
        # change of reference is second order, so a third would move nothing.
        sag_params = post.chain_params(post.full_vector(theta))
        post = factory(mask, sag_params)
        theta, log_sigma = _mode(post, options.error, options.nu, tol, theta0=theta)
    return ModeFit(post, mask, theta, log_sigma, b2s0, link_prior, ident0, lever, sag_params)


def fit_offsets(model: RobotModel, data: Dataset, options: FitOptions = FitOptions(), *, start: ModeFit | None = None,
                progress=None) -> FitResult:
    """Fit joint zero-offsets (and registration corrections and σ) to ``data``. ``start``: where the
    mode's solves start (``fit_mode``); ``progress``: told what the sampler is doing
    (``calib.fit.progress.Progress``, laplace method)."""
    t_start = time.perf_counter()
    mf = fit_mode(model, data, options, start=start)
    post, mask, theta, log_sigma = mf.post, mf.mask, mf.theta, mf.log_sigma
    ident0, lever, n, chain = mf.identifiability_start, mf.lever_mm, model.n_joints, mf.post.chain
    mode = np.concatenate([theta, log_sigma])
    t_mode = time.perf_counter()

    def log_density(x: np.ndarray) -> np.ndarray:
        return post.log_posterior(x[..., : post.dim], x[..., post.dim :])

    if options.method in ("fast", "laplace") and options.linearise_links:
        post.expand(theta)
    elif options.method == "paper" and post.L:
        post.linearise_links(theta)  # paper: only the tool is in it, which the linear form carries exactly
    importance = None
    if options.method == "laplace":
        chains, importance = _sample_laplace(post, theta, log_sigma, options, progress)
    elif options.method == "fast" and options.error == "gaussian":
        chains = _sample_sigma_marginalised(post, theta, log_sigma, options)
    elif options.method == "fast":
        cov = _laplace_covariance(post, theta, log_sigma)
        chains = independence_mh(
            log_density, mode, cov, n_chains=options.n_chains, n_draws=options.n_draws, seed=options.seed
        )
    else:
        unit = np.array([1.0 if nm.rsplit(".", 1)[1] in ("x", "y", "z") else 180.0 / math.pi for nm in post.free_names] + [1.0] * post.S)

        def paper_density(x: np.ndarray) -> np.ndarray:
            sig = x[post.dim :]
            if np.any(sig <= 0):
                return np.array(-np.inf)
            return log_density(np.concatenate([x[: post.dim], np.log(sig)])) - np.log(sig).sum()

        if options.paper_start == "zero":
            x0 = np.concatenate([np.zeros(post.dim), np.ones(post.S)])
        elif options.paper_start == "mode":
            x0 = np.concatenate([theta, np.exp(log_sigma)])
        else:
            raise ValueError(f"paper_start {options.paper_start!r} unknown; use 'zero' or 'mode'")
        raw = paper_metropolis(
            paper_density, x0, unit_scale=unit, n_samples=options.paper_samples, burn_in=options.paper_burn_in, seed=options.seed
        )
        s = raw.samples.copy()
        s[..., post.dim :] = np.log(s[..., post.dim :])
        chains = Chains(s, raw.acceptance, raw.seconds, raw.method)
    t_sample = time.perf_counter()
    expansion_check = dict(post.expansion_check) if options.method in ("fast", "laplace") and options.linearise_links else None
    post.expand(None)  # diagnostics below are exact

    full = post.full_vector(chains.flat[:, : post.dim])
    mean_full = full.mean(axis=0)
    tool_known_std = _std_with_tool_known(post, theta, log_sigma)
    offsets = mean_full[:n]
    std = full[:, :n].std(axis=0, ddof=1)
    ci = np.percentile(full[:, :n], [2.5, 97.5], axis=0).T
    status = []
    max_std = math.radians(options.max_std_deg)
    for i, ax in enumerate(model.axis_names):
        key = f"{ax}.offset"
        if key in mask.reasons:
            r = mask.reasons[key]
            status.append(("fixed: " if r.startswith("not fitted") else "undetermined: ") + r)
            std[i] = np.nan
            ci[i] = np.nan
        elif std[i] > max_std:
            why = f"undetermined: the data determine it only to ±{math.degrees(std[i]):.2f}° (limit {options.max_std_deg}°)"
            known = tool_known_std.get(i)
            if known is not None and known <= max_std:
                why += (f"; it moves the markers like a turn of the tool on the flange, which is known only to "
                        f"±{options.tool_prior_mm:g} mm per coordinate (the tool prior): with the tool's position known it "
                        f"would be ±{math.degrees(known):.3f}° — measure the markers on the flange and give "
                        f"--tool-prior-mm (0: exact)")
            status.append(why)
        else:
            status.append("fitted")
    rot, trans = post.corrections(mean_full)
    b2s = {s: _compose(rot[k], trans[k], post.b2s0[k]) for k, s in enumerate(post.sensors)}
    sig = np.exp(chains.flat[:, post.dim :])
    sigma = {s: (float(sig[:, k].mean()), float(sig[:, k].std(ddof=1))) for k, s in enumerate(post.sensors)}
    ident = _flat_prior_analysis(post, theta, lever)
    robust = sandwich_std(post, theta, log_sigma)
    model_std = np.sqrt(np.diag(_laplace_covariance(post, theta, log_sigma))[: post.dim])
    diag = {
        "method": options.method,
        "sampler": chains.method,
        "n_chains": int(chains.samples.shape[0]),
        "n_draws": int(chains.samples.shape[1]),
        "acceptance": [float(a) for a in chains.acceptance],
        "parameters": post.free_names + [f"{s}.log_sigma" for s in post.sensors],
        "seconds_mode": t_mode - t_start,
        "seconds_sampling": t_sample - t_mode,
        "seconds_total": time.perf_counter() - t_start,
        # method "laplace": the Pareto k̂ of the Laplace Gaussian as an importance proposal (calib.fit.psis).
        "importance": importance,
        # The sampler's predictor against the chain walk at the proposals farthest from the mode (mm).
        "expansion_check": expansion_check,
        "n_measurements": len(data),
        "lever_arm_mm": lever,
        "max_std_deg": options.max_std_deg,
        # Per free θ: sandwich std ÷ the model's (Laplace) std; ≫ 1 means intervals too narrow.
        "sandwich_std_ratio": [float(v) for v in robust / np.where(model_std > 0, model_std, np.nan)],
        "error_budget": error_budget(data, sigma),
        "link_prior": _link_summary(post, chains, options),
        "tool_prior_mm": float(options.tool_prior_mm),
        "tool_degeneracies": _tool_degeneracies(post, theta, lever, options) if post.is_tool.any() else [],
        "gravity_sag": None if options.compliance else _sag_summary(post, theta, sigma),
        "compliance": _compliance_summary(post, full, mask) if options.compliance else None,
    }
    if importance is not None and importance.get("fallback") is None:
        # Weighted draws, resampled: no chains to compare; the effective sample size is the weights'.
        diag["ess"] = [float(importance["ess"])] * chains.samples.shape[-1]
    elif chains.samples.shape[1] >= 4:
        # Split-R-hat also works on one chain (its two halves): it flags a drifting chain.
        diag["rhat"] = [float(v) for v in split_rhat(chains.samples)]
        diag["ess"] = [float(v) for v in effective_sample_size(chains.samples)]
    return FitResult(
        model=model,
        posterior=post,
        chains=chains,
        mode=mode,
        offsets_rad=offsets,
        offsets_std_rad=std,
        offsets_ci95_rad=ci,
        offset_status=status,
        base2sensor=b2s,
        base2sensor0=dict(zip(post.sensors, post.b2s0)),
        sigma_mm=sigma,
        identifiability_start=ident0,
        identifiability=ident,
        diagnostics=diag,
        tool=tool_summary(post, full, options.tool_prior_mm),
    )


#: A compliance known no better than this (rad/(N·m), 1σ) is reported as undetermined: joints of
#: industrial arms yield 1e-6–1e-5 rad/(N·m), torque-sensing arms like the iiwa up to ~2e-4.
MAX_COMPLIANCE_STD = 1e-5


def _compliance_summary(post: OffsetPosterior, full: np.ndarray, mask: ParamMask) -> list[dict]:
    """Per axis: fitted compliance (rad/(N·m)) with std and 95 % interval, or why it is not fitted."""
    out = []
    start = post.n_full - post.C
    for i, ax in enumerate(post.chain.model.axis_names):
        name = f"{ax}.compliance"
        col = full[:, start + i] * 1e-6
        entry = {"joint": ax, "unit": "rad/(N·m)"}
        if name in mask.reasons:
            entry.update(status="undetermined", reason=mask.reasons[name], value=None, std=None, ci95=None)
        elif col.std(ddof=1) > MAX_COMPLIANCE_STD:
            entry.update(status="undetermined", value=None, std=None, ci95=None,
                         reason=f"the data determine it only to ±{col.std(ddof=1):.1g} rad/(N·m) "
                                f"(limit {MAX_COMPLIANCE_STD:g}): add configurations that load this axis")
        else:
            entry.update(status="fitted", reason="", value=float(col.mean()), std=float(col.std(ddof=1)),
                         ci95=[float(v) for v in np.percentile(col, [2.5, 97.5])])
        out.append(entry)
    return out


def _sag_summary(post: OffsetPosterior, theta: np.ndarray, sigma: dict[str, tuple[float, float]]) -> dict | None:
    """Do the residuals lean the way gravity sag would push the markers? (``calib.robot.gravity``)"""
    from calib.robot.gravity import sag_check

    score = sag_check(post, theta, {s: v[0] for s, v in sigma.items()})
    if score is None:
        return None
    return {"statistic": score.statistic, "dof": score.dof, "p_value": score.p_value,
            "significant": score.significant, "joints": score.joints}


def tool_summary(post: OffsetPosterior, full: np.ndarray, prior_mm: float) -> list[dict]:
    """Per fitted marker, its position in the flange frame (mm): nominal, posterior mean, std and
    95 % interval per coordinate, and the prior sd. ``full``: (draws, n_full) posterior draws."""
    start = post.n + 6 * post.S
    chain = post.chain
    out = []
    ms = chain.marker_slice().start
    for m, name in enumerate(chain.marker_names):
        cols = [start + k for k, i in enumerate(post.link_idx) if post.is_tool[k] and (int(i) - ms) // 3 == m]
        if len(cols) != 3:
            continue
        nominal = chain.nominal[ms + 3 * m: ms + 3 * m + 3]
        draws = full[:, cols] + nominal
        out.append({
            "marker": name,
            "nominal_mm": nominal.tolist(),
            "value_mm": draws.mean(axis=0).tolist(),
            "std_mm": draws.std(axis=0, ddof=1).tolist(),
            "ci95_mm": np.percentile(draws, [2.5, 97.5], axis=0).T.tolist(),
            "prior_mm": float(prior_mm),
        })
    return out


def _std_with_tool_known(post: OffsetPosterior, theta: np.ndarray, log_sigma: np.ndarray) -> dict[int, float]:
    """Joint index → the offset's Laplace std (rad) were the tool's position known exactly: the
    conditional covariance with the tool coordinates held (their rows and columns of the precision
    dropped). Empty without a fitted tool."""
    if not post.is_tool.any():
        return {}
    start = post.n + 6 * post.S
    tool_full = set((start + np.flatnonzero(post.is_tool)).tolist())
    keep = np.array([k for k, i in enumerate(post.free) if int(i) not in tool_full])
    j = post.jacobian(theta).reshape(post.n_rows, 3, -1)[..., keep]
    w = np.exp(-2 * log_sigma)[post.sensor_index]
    h = np.einsum("kip,k,kiq->pq", j, w, j) + _prior_precision(post)[np.ix_(keep, keep)]
    cov = np.linalg.pinv(h)
    return {int(post.free[k]): float(np.sqrt(max(cov[a, a], 0.0))) for a, k in enumerate(keep) if post.free[k] < post.n}


def _tool_degeneracies(post: OffsetPosterior, theta: np.ndarray, lever_mm: float, options: FitOptions) -> list[str]:
    """Sentences naming what the data cannot tell apart from a move of the tool on the flange
    (offsets, registration, link parameters against the marker coordinates, all with flat priors at
    the mode): the tool prior decides these combinations; they are not given a spread of their own."""
    from calib.plan.identifiability import analyse

    names = post.free_names
    j = post.jacobian(theta)
    ident = analyse(j, names, _scale(post, lever_mm))
    out = []
    for combo in ident.null_space:
        tool_terms = [k for k in combo.loadings if post.names.index(k) >= post.n + 6 * post.S
                      and post.is_tool[post.names.index(k) - post.n - 6 * post.S]]
        if not tool_terms:
            continue
        how = "exactly" if combo.exact else "almost exactly"
        out.append(f"{combo.describe()}: moves the markers {how} alike — decided by the priors (tool ±{options.tool_prior_mm:g} mm"
                   + (f", links ±{options.link_tolerance[0]:g} mm / ±{options.link_tolerance[1]:g}°"
                      if options.link_tolerance and options.method != "paper" else "") + ")")
    # The last link's parameters that only move the tool are kept nominal (``_resolve_rigid_links``):
    # the fitted markers carry them.
    out += [f"{name}: {why}" for name, why in post.mask.reasons.items() if "the tool takes it" in why]
    return out


def _link_summary(post: OffsetPosterior, chains: Chains, options: FitOptions) -> dict | None:
    """The marginalised link parameters: prior and posterior deviation from nominal (mm / deg)."""
    pos, _ = post.link_free()
    start = post.n + 6 * post.S
    pos = np.array([p for p in pos if not post.is_tool[post.free[p] - start]], dtype=int)
    if not pos.size or options.link_tolerance is None:
        return None
    draws = chains.flat[:, pos]
    out = {}
    for k, p in enumerate(pos):
        name = post.free_names[p]
        scale = 1.0 if name.rsplit(".", 1)[1] in ("d", "a") else 180.0 / math.pi
        out[name] = {"mean": float(draws[:, k].mean() * scale), "std": float(draws[:, k].std(ddof=1) * scale)}
    length_mm, angle_deg = options.link_tolerance
    return {"length_mm": length_mm, "angle_deg": angle_deg, "parameters": out}


def error_budget(data: Dataset, sigma: dict[str, tuple[float, float]]) -> dict[str, dict]:
    """Per sensor: how much of the fitted σ the sensor's own noise explains.

    ``noise_mm`` is the RMS standard error of the averaged positions (std_mm / √n per row, where
    the data carries them). The rest, ``unmodelled_mm`` = √(σ² − noise²), is robot error the
    zero-offset model does not describe (link errors, deflection, backlash). The posterior
    treats it as independent from configuration to configuration; where it is systematic the
    offsets are biased beyond their intervals — compare with ``--method full``.
    """
    out = {}
    for s, (sig, _) in sigma.items():
        rows = data.sensor == s
        std, n = data.std_mm[rows], data.count[rows]
        ok = np.isfinite(std) & (n > 0)
        noise = float(np.sqrt(np.mean((std[ok] / np.sqrt(n[ok])) ** 2))) if ok.any() else None
        spread = float(np.sqrt(np.mean(std[ok] ** 2))) if ok.any() else None
        # sample_spread_mm: the rms per-axis spread of one sample (std_mm): the floor a model's
        # held-out error is judged against (the arm's own settling and vibration are in it).
        entry: dict = {"sigma_mm": sig, "noise_mm": noise, "sample_spread_mm": spread, "n_rows": int(rows.sum())}
        if noise is not None:
            unmodelled = math.sqrt(max(sig**2 - noise**2, 0.0))
            entry["unmodelled_mm"] = unmodelled
            entry["unmodelled_share"] = unmodelled**2 / sig**2 if sig > 0 else 0.0
        out[s] = entry
    return out


def _compose(rot: np.ndarray, trans: np.ndarray, b2s0: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = trans
    return t @ b2s0
