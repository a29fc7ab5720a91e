"""Sensor↔robot registration: the ``base2sensor`` transform from corresponding points.

A registration is a 4×4 rigid transform ``base2sensor`` with
``p_sensor = apply(base2sensor, p_base)`` (mm). Every function takes the same points twice:
``p_base`` shape (n, 3), mm, as the robot reports them in its base frame (R in the seeds), and
``p_sensor`` shape (n, 3), mm, as the reference sensor measured them (N in the seeds).

Methods, from ``registration-strategies`` (Van Wyk & Marvel, IEEE T-ASE 2018) unless noted:

``register_three_points``   the H(·) operator, eqs. (1)–(5), Sec. III-A: a frame O built from
                            three non-collinear points in each system, ``H_RN = H_ON · H_OR⁻¹``.
``register_combinatorial``  redundant combinatorial averaging, eqs. (6)–(7), Sec. III-B: H(·) of
                            every non-collinear triple, averaged with a *proper* rotation mean
                            (the seed's element-wise mean (6) is not a rotation; the seed itself
                            points to Moakher [17] for separate rotation averaging).
``refine_annealing``        simulated annealing, eqs. (8)–(15), Sec. III-C: a correction
                            ``H_RR(Θ)`` applied on the base side of an initial registration,
                            acceptance from the posterior (14), cooling ``T_τ = 1/(C ln τ)`` (15).
``register_clustered``      clustering kernels, eqs. (16)–(17), Sec. III-D: k-means kernels in
                            the sensor frame, one averaged registration per kernel.
``register_least_squares``  SVD (Kabsch/Horn) least squares, the baseline the design asks for.

The initial registration of ``remastering-in-situ`` Sec. IV, eq. (8) is
``register_three_points`` on three points of the optimisation set; that paper then refines it
together with the zero-offsets (the fitter's job, not this module's).
"""

from __future__ import annotations

import itertools
import logging
import math
from dataclasses import dataclass

import numpy as np

from calib.robot.transforms import apply, homogeneous, invert, pose_to_matrix

log = logging.getLogger(__name__)

#: Default degeneracy tolerance, mm. Two points closer than this are "coincident"; a third
#: point closer than this to the line through the first two makes the triple "collinear".
COLLINEAR_TOL_MM = 1e-6

#: Largest number of triples enumerated explicitly before random triples are drawn instead.
_ENUMERATE_LIMIT = 2_000_000


@dataclass(frozen=True)
class RegistrationResult:
    """One registration and how well it fits the points it was computed from.

    base2sensor: (4, 4) rigid transform, mm; ``p_sensor ≈ apply(base2sensor, p_base)``.
    residuals_mm: (n,) distances |apply(base2sensor, p_base_i) − p_sensor_i|, mm (the seed's
        translation error e on the training points).
    rms_mm: root mean square of ``residuals_mm``, mm.
    method: name of the method that produced it.
    n_triples: number of 3-point registrations averaged (1 for the 3-point method, 0 for
        methods that use no triples).
    """

    base2sensor: np.ndarray
    residuals_mm: np.ndarray
    rms_mm: float
    method: str
    n_triples: int

    @classmethod
    def from_transform(
        cls, base2sensor: np.ndarray, p_base: np.ndarray, p_sensor: np.ndarray, method: str, n_triples: int
    ) -> RegistrationResult:
        """Build a result, computing the residuals of ``base2sensor`` on the given points."""
        res = translation_errors(base2sensor, p_base, p_sensor)
        return cls(
            base2sensor=np.asarray(base2sensor, dtype=float),
            residuals_mm=res,
            rms_mm=float(np.sqrt(np.mean(res**2))),
            method=method,
            n_triples=int(n_triples),
        )


# --------------------------------------------------------------------------------------------
# input checks


def _points(name: str, p: object, n: int | None = None, min_n: int = 1) -> np.ndarray:
    """Validate a point array: shape (n, 3), finite, at least ``min_n`` rows."""
    try:
        a = np.asarray(p, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be an array of numbers with shape (n, 3) in mm; got {type(p).__name__}") from exc
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3) (one xyz point per row, mm); got shape {a.shape}")
    if n is not None and a.shape[0] != n:
        raise ValueError(f"{name} must have shape ({n}, 3); got shape {a.shape}")
    if a.shape[0] < min_n:
        raise ValueError(f"{name} needs at least {min_n} points; got {a.shape[0]}")
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        raise ValueError(f"{name} holds non-finite values (NaN or inf) in rows {np.flatnonzero(bad).tolist()}")
    return a


def _pair(p_base: object, p_sensor: object, min_n: int) -> tuple[np.ndarray, np.ndarray]:
    """Validate corresponding point sets: both (n, 3), same n ≥ min_n, finite."""
    b = _points("p_base", p_base, min_n=min_n)
    s = _points("p_sensor", p_sensor)
    if s.shape != b.shape:
        raise ValueError(
            f"p_base and p_sensor must hold the same points (same shape); got {b.shape} and {s.shape}"
        )
    return b, s


def _transform(name: str, t: object, tol: float = 1e-6) -> np.ndarray:
    """Validate a (4, 4) rigid transform (orthonormal rotation, det +1, last row 0 0 0 1)."""
    if isinstance(t, RegistrationResult):
        t = t.base2sensor
    a = np.asarray(t, dtype=float)
    if a.shape != (4, 4):
        raise ValueError(f"{name} must be a (4, 4) homogeneous transform; got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} holds non-finite values")
    r = a[:3, :3]
    err = float(np.abs(r.T @ r - np.eye(3)).max())
    if err > tol or np.linalg.det(r) < 0 or not np.allclose(a[3], [0, 0, 0, 1], atol=tol):
        raise ValueError(
            f"{name} must be a rigid transform (orthonormal rotation with det +1, last row 0 0 0 1); "
            f"got |RᵀR − I|max = {err:.3g}, det = {np.linalg.det(r):.6g}, last row {a[3].tolist()}"
        )
    return a


def translation_errors(base2sensor: np.ndarray, p_base: np.ndarray, p_sensor: np.ndarray) -> np.ndarray:
    """Translation error e_i = |apply(base2sensor, p_base_i) − p_sensor_i|, shape (n,), mm.

    This is the seed's performance measure (Sec. II-B): the Euclidean distance, in the sensor
    frame N, between where the registration puts the robot's point and where the sensor saw it.
    """
    t = _transform("base2sensor", base2sensor)
    b, s = _pair(p_base, p_sensor, min_n=1)
    return np.linalg.norm(apply(t, b) - s, axis=1)


# --------------------------------------------------------------------------------------------
# the H(·) operator, eqs. (1)–(5)


def _frames(p: np.ndarray, tol_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched eqs. (2)–(5): frames (q, 4, 4) of triples p (q, 3, 3), with the base length
    |p2 − p1| (q,) and the height of p3 off the line p1p2 (q,), both mm."""
    d12 = p[:, 1] - p[:, 0]
    base = np.linalg.norm(d12, axis=1)
    x = d12 / np.where(base > tol_mm, base, 1.0)[:, None]
    c = np.cross(x, p[:, 2] - p[:, 0])
    height = np.linalg.norm(c, axis=1)
    height = np.where(base > tol_mm, height, 0.0)
    y = c / np.where(height > tol_mm, height, 1.0)[:, None]
    z = np.cross(x, y)
    return homogeneous(np.stack([x, y, z], axis=-1), p[:, 0]), base, height


def three_point_frame(p: np.ndarray, tol_mm: float = COLLINEAR_TOL_MM) -> np.ndarray:
    """The frame O of three points, eqs. (2)–(5): ``H_O`` (4, 4) in the points' own frame.

    p: (3, 3), one point per row, mm. Origin at p1; x̂ along p2 − p1; ŷ along x̂ × (p3 − p1)
    (eq. 4 as the seed writes it: normal to the points' plane); ẑ = x̂ × ŷ (in the plane).

    Raises ValueError when |p2 − p1| ≤ ``tol_mm`` (coincident points) or when p3 lies within
    ``tol_mm`` of the line through p1 and p2 (collinear points): no frame is defined then.
    """
    a = _points("p", p, n=3)
    if not tol_mm > 0:
        raise ValueError(f"tol_mm must be a positive length in mm; got {tol_mm!r}")
    frame, base, height = _frames(a[None], tol_mm)
    if base[0] <= tol_mm:
        raise ValueError(
            f"points 1 and 2 coincide: |p2 − p1| = {base[0]:.3g} mm ≤ tol_mm = {tol_mm:.3g} mm; "
            "the three points must be distinct and not collinear"
        )
    if height[0] <= tol_mm:
        raise ValueError(
            f"points are collinear: point 3 lies {height[0]:.3g} mm from the line through points 1 and 2 "
            f"(tolerance tol_mm = {tol_mm:.3g} mm); choose a third point off that line"
        )
    return frame[0]


def register_three_points(
    p_base: np.ndarray, p_sensor: np.ndarray, tol_mm: float = COLLINEAR_TOL_MM
) -> RegistrationResult:
    """The seed's H(·) operator, eq. (1): ``H_RN = H_ON · (H_OR)⁻¹`` from three points.

    p_base, p_sensor: (3, 3), corresponding points (one per row), mm. The result maps point 1
    exactly, aligns the direction 1→2 exactly and the plane of the three points; all the
    measurement error of those three points goes into the registration (Sec. III-A), which is
    why the other methods exist. Raises ValueError for coincident or collinear points in either
    set (tolerance ``tol_mm``, see ``three_point_frame``).
    """
    b, s = _pair(p_base, p_sensor, min_n=3)
    if b.shape[0] != 3:
        raise ValueError(f"register_three_points takes exactly 3 points; got {b.shape[0]} (use register_combinatorial)")
    try:
        h_or = three_point_frame(b, tol_mm)
    except ValueError as exc:
        raise ValueError(f"p_base: {exc}") from exc
    try:
        h_on = three_point_frame(s, tol_mm)
    except ValueError as exc:
        raise ValueError(f"p_sensor: {exc}") from exc
    return RegistrationResult.from_transform(h_on @ invert(h_or), b, s, "three_point", 1)


# --------------------------------------------------------------------------------------------
# averaging on SO(3)


def chordal_mean_rotation(rotations: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Chordal L2 mean of rotations (q, 3, 3): the rotation nearest (Frobenius) to Σ wᵢRᵢ.

    Moakher's projected arithmetic mean [17 in the registration seed]: the element-wise mean
    of eq. (6), projected back onto SO(3) by SVD, ``U · diag(1, 1, det(UVᵀ)) · Vᵀ``. Always a
    proper rotation (RᵀR = I, det +1). Weights (q,) are non-negative, default equal.
    """
    r = np.asarray(rotations, dtype=float)
    if r.ndim != 3 or r.shape[1:] != (3, 3) or r.shape[0] < 1:
        raise ValueError(f"rotations must have shape (q, 3, 3) with q ≥ 1; got {r.shape}")
    w = np.ones(r.shape[0]) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (r.shape[0],) or not np.isfinite(w).all() or (w < 0).any() or w.sum() <= 0:
        raise ValueError(f"weights must be {r.shape[0]} finite non-negative numbers, not all zero; got {w!r}")
    m = np.einsum("q,qij->ij", w, r) / w.sum()
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def average_transforms(transforms: np.ndarray) -> np.ndarray:
    """Average rigid transforms (q, 4, 4): chordal mean rotation and mean translation → (4, 4).

    This is eq. (6)/(16) with the rotation averaged separately, as the seed recommends for
    anything but "extremely small rotational deviations".
    """
    t = np.asarray(transforms, dtype=float)
    if t.ndim != 3 or t.shape[1:] != (4, 4) or t.shape[0] < 1:
        raise ValueError(f"transforms must have shape (q, 4, 4) with q ≥ 1; got {t.shape}")
    return homogeneous(chordal_mean_rotation(t[:, :3, :3]), t[:, :3, 3].mean(axis=0))


# --------------------------------------------------------------------------------------------
# redundant combinatorial averaging, eqs. (6)–(7)


def _triples(m: int, max_triples: int | None, rng: np.random.Generator) -> np.ndarray:
    """Index triples j < k < l (t, 3): all C(m, 3), or ``max_triples`` distinct ones at random."""
    total = math.comb(m, 3)
    if max_triples is None or total <= max_triples:
        return np.array(list(itertools.combinations(range(m), 3)), dtype=int).reshape(-1, 3)
    if total <= _ENUMERATE_LIMIT:
        every = np.array(list(itertools.combinations(range(m), 3)), dtype=int)
        return every[np.sort(rng.choice(total, size=max_triples, replace=False))]
    chosen: set[tuple[int, int, int]] = set()
    for _ in range(100):  # bounded: each round draws a batch, duplicates are rare when total ≫ max
        batch = np.sort(np.stack([rng.choice(m, 3, replace=False) for _ in range(max_triples)]), axis=1)
        chosen.update(map(tuple, batch.tolist()))
        if len(chosen) >= max_triples:
            break
    return np.array(sorted(chosen)[:max_triples], dtype=int)


def triple_registrations(
    p_base: np.ndarray, p_sensor: np.ndarray, triples: np.ndarray, tol_mm: float = COLLINEAR_TOL_MM
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (7): H(·) of each index triple. Returns (transforms (t, 4, 4), valid (t,) bool).

    A triple is invalid (its transform is the identity placeholder, ``valid`` False) when it is
    coincident or collinear within ``tol_mm`` in either point set.
    """
    idx = np.asarray(triples, dtype=int)
    f_r, base_r, height_r = _frames(p_base[idx], tol_mm)
    f_n, base_n, height_n = _frames(p_sensor[idx], tol_mm)
    valid = (base_r > tol_mm) & (height_r > tol_mm) & (base_n > tol_mm) & (height_n > tol_mm)
    h = f_n @ invert(f_r)
    h[~valid] = np.eye(4)
    return h, valid


def register_combinatorial(
    p_base: np.ndarray,
    p_sensor: np.ndarray,
    max_triples: int | None = None,
    rng: np.random.Generator | int | None = None,
    tol_mm: float = COLLINEAR_TOL_MM,
) -> RegistrationResult:
    """Redundant combinatorial averaging, eqs. (6)–(7) of the registration seed (Sec. III-B).

    p_base, p_sensor: (M, 3), M ≥ 3 corresponding points, mm.
    max_triples: if C(M, 3) exceeds it, that many distinct triples are drawn at random with
        ``rng`` (a Generator or a seed; None means seed 0, so results are reproducible).
    tol_mm: triples coincident/collinear within this (either set) are left out, as eq. (7)
        assumes non-collinear triples.

    Every 3-point registration H(·) is computed and averaged: the rotation by its chordal L2
    mean projected onto SO(3) (``chordal_mean_rotation``), the translation by its arithmetic
    mean. ``n_triples`` in the result is the number of triples actually averaged.
    """
    b, s = _pair(p_base, p_sensor, min_n=3)
    if max_triples is not None and (int(max_triples) != max_triples or max_triples < 1):
        raise ValueError(f"max_triples must be a positive integer or None; got {max_triples!r}")
    gen = np.random.default_rng(0 if rng is None else rng)
    idx = _triples(b.shape[0], max_triples, gen)
    h, valid = triple_registrations(b, s, idx, tol_mm)
    if not valid.any():
        raise ValueError(
            f"all {len(idx)} point triples are coincident or collinear within tol_mm = {tol_mm:.3g} mm; "
            "registration needs at least three points that are not on one line"
        )
    if (~valid).any():
        log.debug("combinatorial registration: %d of %d triples collinear, left out", int((~valid).sum()), len(idx))
    avg = average_transforms(h[valid])
    return RegistrationResult.from_transform(avg, b, s, "combinatorial", int(valid.sum()))


# --------------------------------------------------------------------------------------------
# least squares


def register_least_squares(
    p_base: np.ndarray, p_sensor: np.ndarray, weights: np.ndarray | None = None, tol_mm: float = COLLINEAR_TOL_MM
) -> RegistrationResult:
    """Weighted least-squares rigid registration by SVD (Kabsch 1976 / Horn 1987).

    Minimises Σ wᵢ |R p_base_i + t − p_sensor_i|² over proper rotations (det +1; a reflection is
    never returned) and translations.

    p_base, p_sensor: (n, 3), n ≥ 3, mm. weights: (n,) finite, non-negative, at least three
    positive; default equal. Raises ValueError if the weighted points lie on one line within
    ``tol_mm`` (RMS distance to their best-fit line), where the rotation about that line is
    undetermined.
    """
    b, s = _pair(p_base, p_sensor, min_n=3)
    n = b.shape[0]
    if weights is None:
        w = np.ones(n)
    else:
        w = np.asarray(weights, dtype=float)
        if w.shape != (n,):
            raise ValueError(f"weights must have shape ({n},) (one per point); got {w.shape}")
        if not np.isfinite(w).all() or (w < 0).any():
            raise ValueError("weights must be finite and non-negative")
        if (w > 0).sum() < 3:
            raise ValueError(f"at least 3 weights must be positive; got {(w > 0).sum()}")
    wn = w / w.sum()
    cb, cs = wn @ b, wn @ s
    db, ds = b - cb, s - cs
    for name, d in (("p_base", db), ("p_sensor", ds)):
        sv = np.linalg.svd(np.sqrt(wn)[:, None] * d, compute_uv=False)
        off_line = float(np.sqrt(sv[1] ** 2 + sv[2] ** 2))
        if off_line <= tol_mm:
            raise ValueError(
                f"{name}: points are collinear (RMS distance to their best-fit line {off_line:.3g} mm "
                f"≤ tol_mm = {tol_mm:.3g} mm); the rotation about that line is undetermined"
            )
    u, _, vt = np.linalg.svd((wn[:, None] * db).T @ ds)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return RegistrationResult.from_transform(homogeneous(r, cs - r @ cb), b, s, "least_squares", 0)


# --------------------------------------------------------------------------------------------
# simulated annealing, eqs. (8)–(15)


@dataclass(frozen=True)
class AnnealingResult:
    """Outcome of ``refine_annealing``.

    registration: the best registration visited (never worse than the start, by cost (9)).
    theta: (6,) best correction Θ = (x, y, z mm, α, β, γ rad), eq. (10).
    sigma_mm: σ of the chain's state when the best Θ was visited, mm.
    initial_cost_mm2, best_cost_mm2: cost (9) Σ|Eᵢ|² at the start and at the best Θ, mm².
    acceptance_rate: fraction of proposals accepted.
    n_iterations: proposals made.
    """

    registration: RegistrationResult
    theta: np.ndarray
    sigma_mm: float
    initial_cost_mm2: float
    best_cost_mm2: float
    acceptance_rate: float
    n_iterations: int


def correction_matrix(theta: np.ndarray) -> np.ndarray:
    """H_RR(Θ) of eq. (10): Θ = (x, y, z mm, α, β, γ rad) → (4, 4).

    α about x, β about y, γ about z, Euler ZYX: R = Rz(γ) Ry(β) Rx(α); translation (x, y, z).
    """
    th = np.asarray(theta, dtype=float)
    if th.shape != (6,):
        raise ValueError(f"theta must have shape (6,) = (x, y, z, α, β, γ); got {th.shape}")
    return pose_to_matrix(th[:3], th[5:2:-1])


def refine_annealing(
    p_base: np.ndarray,
    p_sensor: np.ndarray,
    initial: np.ndarray | RegistrationResult,
    rng: np.random.Generator | int,
    n_iterations: int = 20_000,
    cooling_c: float = 2.0,
    step_mm: float = 0.0125,
    step_rad: float = math.radians(0.0125),
    sigma0_mm: float = 1.0,
    sigma_step_mm: float = 0.0125,
) -> AnnealingResult:
    """Simulated-annealing refinement of a registration, Sec. III-C of the registration seed.

    The model is eq. (10): ``p_sensor,robot = H_RN · H_RR(Θ) · p_base`` with ``H_RN`` the
    ``initial`` registration (4, 4) and Θ = {x, y, z, α, β, γ} a small base-side correction
    (``correction_matrix``). The cost is eq. (9), E = Σᵢ |Eᵢ|² with Eᵢ = p_sensor,i −
    p_sensor,robot,i (mm²). The target density is the posterior (14),
    ``p(Θ, σ² | P_ref) ∝ σ^(−n−2) exp(−E / 2σ²)`` (Gaussian errors (11), prior ∝ σ⁻²), so σ is
    sampled together with Θ. A proposal is accepted with probability
    ``min(1, [p(new)/p(old)]^(1/T_τ))`` under the cooling schedule eq. (15),
    ``T_τ = 1 / (C ln τ)``, τ = 1 … n_iterations, C = ``cooling_c`` (paper: C = 2); at τ = 1 the
    temperature is infinite and the first proposal is always accepted.

    Proposals are symmetric uniform random walks, as in ``remastering-in-situ`` Sec. IV (its
    defaults: half-width 0.0125 mm for translations, 0.0125° for angles, 0.0125 mm for σ,
    σ starting at 1 mm, Θ starting at 0). The registration seed gives no proposal widths or
    iteration count ("within a few seconds"); ``n_iterations`` defaults to 20 000.

    p_base, p_sensor: (n, 3), n ≥ 3, mm. rng: Generator or seed (required: runs are seeded).
    The best Θ by cost (9) over the whole chain, the start included, is returned, so the
    result is never worse than ``initial`` on these points.
    """
    b, s = _pair(p_base, p_sensor, min_n=3)
    h0 = _transform("initial", initial)
    if int(n_iterations) != n_iterations or n_iterations < 1:
        raise ValueError(f"n_iterations must be a positive integer; got {n_iterations!r}")
    for name, v in (("cooling_c", cooling_c), ("step_mm", step_mm), ("step_rad", step_rad),
                    ("sigma0_mm", sigma0_mm), ("sigma_step_mm", sigma_step_mm)):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a positive finite number; got {v!r}")
    gen = np.random.default_rng(rng)
    n = b.shape[0]
    # E(Θ) = Σ |A(RΘ p + tΘ) + a − s|² = Σ |RΘ p + tΘ − Aᵀ(s − a)|²  (A orthonormal)
    target = (s - h0[:3, 3]) @ h0[:3, :3]

    def cost(th: np.ndarray) -> float:
        ca, sa = math.cos(th[3]), math.sin(th[3])
        cb, sb = math.cos(th[4]), math.sin(th[4])
        cg, sg = math.cos(th[5]), math.sin(th[5])
        r = np.array(  # Rz(γ) Ry(β) Rx(α), written out: this is the hot loop
            [
                [cg * cb, cg * sb * sa - sg * ca, cg * sb * ca + sg * sa],
                [sg * cb, sg * sb * sa + cg * ca, sg * sb * ca - cg * sa],
                [-sb, cb * sa, cb * ca],
            ]
        )
        d = b @ r.T + (th[:3] - target)
        return float(np.einsum("ij,ij->", d, d))

    def log_post(e: float, sig: float) -> float:
        return -(n + 2) * math.log(sig) - e / (2.0 * sig * sig)

    theta = np.zeros(6)
    sigma = float(sigma0_mm)
    e = cost(theta)
    lp = log_post(e, sigma)
    best_theta, best_e, best_sigma = theta.copy(), e, sigma
    e0 = e
    half = np.array([step_mm] * 3 + [step_rad] * 3 + [sigma_step_mm])
    steps = gen.uniform(-1.0, 1.0, size=(int(n_iterations), 7)) * half
    log_u = np.log(gen.uniform(size=int(n_iterations)))
    accepted = 0
    for tau in range(1, int(n_iterations) + 1):
        th_new = theta + steps[tau - 1, :6]
        sig_new = sigma + steps[tau - 1, 6]
        if sig_new <= 0.0:
            continue
        e_new = cost(th_new)
        lp_new = log_post(e_new, sig_new)
        inv_t = cooling_c * math.log(tau)  # 1 / T_τ, eq. (15)
        if inv_t == 0.0 or log_u[tau - 1] < (lp_new - lp) * inv_t:
            theta, sigma, e, lp = th_new, sig_new, e_new, lp_new
            accepted += 1
            if e < best_e:
                best_theta, best_e, best_sigma = theta.copy(), e, sigma
    h_best = h0 @ correction_matrix(best_theta)
    log.debug("annealing: cost %.6g → %.6g mm², %d/%d accepted", e0, best_e, accepted, n_iterations)
    return AnnealingResult(
        registration=RegistrationResult.from_transform(h_best, b, s, "annealing", 0),
        theta=best_theta,
        sigma_mm=best_sigma,
        initial_cost_mm2=e0,
        best_cost_mm2=best_e,
        acceptance_rate=accepted / int(n_iterations),
        n_iterations=int(n_iterations),
    )


# --------------------------------------------------------------------------------------------
# clustering kernels, eqs. (16)–(17)


def kmeans(
    points: np.ndarray, k: int, rng: np.random.Generator | int | None = None, max_iterations: int = 100
) -> tuple[np.ndarray, np.ndarray]:
    """Lloyd's k-means [18] with k-means++ seeding: (centroids (k, 3), labels (M,)).

    points: (M, 3), mm, M ≥ k. Stops when the assignment no longer changes or after
    ``max_iterations``. An emptied cluster is re-seeded with the point farthest from its
    centroid. rng: Generator or seed (None means seed 0).
    """
    p = _points("points", points)
    if int(k) != k or k < 1 or k > p.shape[0]:
        raise ValueError(f"k must be an integer between 1 and the number of points ({p.shape[0]}); got {k!r}")
    gen = np.random.default_rng(0 if rng is None else rng)
    k = int(k)
    centroids = [p[gen.integers(p.shape[0])]]
    for _ in range(1, k):
        d2 = np.min(((p[:, None, :] - np.array(centroids)[None]) ** 2).sum(-1), axis=1)
        total = d2.sum()
        i = gen.choice(p.shape[0], p=d2 / total) if total > 0 else gen.integers(p.shape[0])
        centroids.append(p[i])
    c = np.array(centroids, dtype=float)
    labels = np.full(p.shape[0], -1)
    for _ in range(int(max_iterations)):
        d2 = ((p[:, None, :] - c[None]) ** 2).sum(-1)
        new = np.argmin(d2, axis=1)
        own = d2[np.arange(p.shape[0]), new]
        for j in range(k):
            if not (new == j).any():
                far = int(np.argmax(own))
                new[far], own[far] = j, -1.0
        if np.array_equal(new, labels):
            break
        labels = new
        c = np.array([p[labels == j].mean(axis=0) for j in range(k)])
    return c, labels


@dataclass(frozen=True)
class ClusteredRegistration:
    """Registration kernels, Sec. III-D: one averaged registration per k-means cluster.

    kernels_sensor: (k, 3) cluster centroids N p_c in the sensor frame, mm.
    kernels_base: (k, 3) the matching mean robot points R p_c in the base frame, mm.
    base2sensor: (k, 4, 4) the registration H_RN^c of each kernel (eq. 16).
    n_triples: (k,) number of 3-point registrations averaged per kernel.
    full_set: (k,) True where the kernel uses the whole registration set (M ≤ 3k, or the
        cluster had no non-collinear triple) instead of its own members.
    labels: (M,) kernel of each training point.
    residuals_mm: (M,) translation error of each training point under its own kernel, mm.
    """

    kernels_sensor: np.ndarray
    kernels_base: np.ndarray
    base2sensor: np.ndarray
    n_triples: np.ndarray
    full_set: np.ndarray
    labels: np.ndarray
    residuals_mm: np.ndarray

    @property
    def rms_mm(self) -> float:
        """RMS of the training residuals, mm."""
        return float(np.sqrt(np.mean(self.residuals_mm**2)))

    def kernel_for_sensor(self, points_sensor: np.ndarray) -> np.ndarray:
        """Index (...,) of the nearest kernel to target points (..., 3) in the sensor frame."""
        p = np.asarray(points_sensor, dtype=float)
        return np.argmin(np.linalg.norm(p[..., None, :] - self.kernels_sensor, axis=-1), axis=-1)

    def kernel_for_base(self, points_base: np.ndarray) -> np.ndarray:
        """Index (...,) of the nearest kernel to points (..., 3) given in the base frame."""
        p = np.asarray(points_base, dtype=float)
        return np.argmin(np.linalg.norm(p[..., None, :] - self.kernels_base, axis=-1), axis=-1)

    def sensor_to_base(self, points_sensor: np.ndarray) -> np.ndarray:
        """The seed's use (end of Sec. III-D): where the robot must go, (..., 3) mm in the base
        frame, to put its TCP at target points (..., 3) in the sensor frame, each through the
        registration of its nearest kernel."""
        p = np.asarray(points_sensor, dtype=float)
        return apply(invert(self.base2sensor[self.kernel_for_sensor(p)]), p)

    def base_to_sensor(self, points_base: np.ndarray) -> np.ndarray:
        """Points (..., 3) in the base frame → sensor frame, through the kernel nearest in the
        base frame."""
        p = np.asarray(points_base, dtype=float)
        return apply(self.base2sensor[self.kernel_for_base(p)], p)


def register_clustered(
    p_base: np.ndarray,
    p_sensor: np.ndarray,
    n_clusters: int,
    rng: np.random.Generator | int | None = None,
    tol_mm: float = COLLINEAR_TOL_MM,
    max_iterations: int = 100,
) -> ClusteredRegistration:
    """Clustering registration kernels, eqs. (16)–(17) of the registration seed (Sec. III-D).

    The sensor-frame points are clustered by k-means (``kmeans``, k = ``n_clusters``, seeded
    by ``rng``; None means seed 0). Kernel c is rooted at the centroid N p_c of its members,
    paired with the mean R p_c of their robot points (a rigid map sends means to means, so the
    pair is a valid correspondence). Its registration is eq. (16): the average of
    H({N p_c, N p_g, N p_h}, {R p_c, R p_g, R p_h}) over member pairs g < h (eq. 17), with the
    rotation averaged properly (chordal mean) as for ``register_combinatorial``.

    As the seed directs, the entire registration set (all C(M, 3) triples) is used instead when
    M ≤ 3k, and for any cluster that has no non-collinear (centroid, g, h) triple (fewer than
    two members, or all members on a line through the centroid).

    p_base, p_sensor: (M, 3), M ≥ 3, mm. Note the seed's robot attributes live in ℝ⁶ (poses);
    here the robot side is the 3-D point, which is all the H(·) operator uses.
    """
    b, s = _pair(p_base, p_sensor, min_n=3)
    m = b.shape[0]
    if int(n_clusters) != n_clusters or not 1 <= n_clusters <= m:
        raise ValueError(f"n_clusters must be an integer between 1 and the number of points ({m}); got {n_clusters!r}")
    k = int(n_clusters)
    centroids_s, labels = kmeans(s, k, rng, max_iterations)
    centroids_b = np.array([b[labels == c].mean(axis=0) for c in range(k)])
    full: RegistrationResult | None = None

    def whole_set() -> RegistrationResult:
        nonlocal full
        if full is None:
            full = register_combinatorial(b, s, tol_mm=tol_mm)
        return full

    h = np.zeros((k, 4, 4))
    n_tri = np.zeros(k, dtype=int)
    used_full = np.zeros(k, dtype=bool)
    for c in range(k):
        members = np.flatnonzero(labels == c)
        if m > 3 * k and members.size >= 2:
            pairs = np.array(list(itertools.combinations(members, 2)), dtype=int)
            tb = np.concatenate([np.broadcast_to(centroids_b[c], (len(pairs), 1, 3)), b[pairs]], axis=1)
            ts = np.concatenate([np.broadcast_to(centroids_s[c], (len(pairs), 1, 3)), s[pairs]], axis=1)
            fb, base_b, height_b = _frames(tb, tol_mm)
            fs, base_s, height_s = _frames(ts, tol_mm)
            ok = (base_b > tol_mm) & (height_b > tol_mm) & (base_s > tol_mm) & (height_s > tol_mm)
            if ok.any():
                h[c] = average_transforms((fs @ invert(fb))[ok])
                n_tri[c] = int(ok.sum())
                continue
        w = whole_set()
        h[c], n_tri[c], used_full[c] = w.base2sensor, w.n_triples, True
    res = np.linalg.norm(apply(h[labels], b) - s, axis=1)
    return ClusteredRegistration(
        kernels_sensor=centroids_s,
        kernels_base=centroids_b,
        base2sensor=h,
        n_triples=n_tri,
        full_set=used_full,
        labels=labels,
        residuals_mm=res,
    )
