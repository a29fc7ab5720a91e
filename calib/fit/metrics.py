"""Accuracy metrics of the remastering paper, before and after a fit (all in mm).

``relative_errors``    eq. 17: within each pose group, every pair of configurations (same sensor,
                       same marker): | |p_ref,i − p_ref,j| − |p_robot,i − p_robot,j| |. Needs no
                       registration — distances are frame-independent.
``absolute_errors``    eq. 18: per point |E_i| after a least-squares rigid registration of the
                       robot's predicted points to the measured ones (per sensor).
``registered_errors``  per point |E_i| with a given registration per sensor — how validation points
                       are scored: with the registration of the *calibration* data, never one fitted
                       to the points being scored (which would absorb part of their error).
``theoretical_errors`` Sec. V-C, Tables V–VII: distances between the TCP with the estimated
                       offsets (or the nominal "before" ones) and the TCP with posterior draws of
                       the offsets, with and without the isotropic error σ, at given
                       configurations. The TCP is the flange origin.
Each metric is summarised as mean, 2.5/97.5 percentiles and maximum.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from calib.measure.dataset import Dataset
from calib.robot.kinematics import Chain, offset_kinematics
from calib.fit.registration import register_least_squares
from calib.robot.transforms import apply


@dataclass(frozen=True)
class Summary:
    """mm. ``mc_se``: the Monte-Carlo standard error of ``mean`` where the values are random
    draws (the theoretical metrics), else None (and left out of ``to_dict``)."""

    mean: float
    p2_5: float
    p97_5: float
    max: float
    count: int
    mc_se: float | None = None

    def to_dict(self) -> dict:
        out = asdict(self)
        if self.mc_se is None:
            del out["mc_se"]
        return out


def summarize(values: np.ndarray, mc_se: float | None = None) -> Summary:
    v = np.asarray(values, dtype=float).ravel()
    if v.size == 0:
        nan = float("nan")
        return Summary(nan, nan, nan, nan, 0, mc_se)
    lo, hi = np.percentile(v, [2.5, 97.5])
    return Summary(float(v.mean()), float(lo), float(hi), float(v.max()), int(v.size), mc_se)


def predicted_base(chain: Chain, data: Dataset, offsets_rad: np.ndarray, *,
                   markers_mm: dict[str, np.ndarray] | None = None) -> np.ndarray:
    """The robot's idea of each row's marker in its base frame, (k, 3) mm: the model with
    ``offsets_rad`` (n,) and, for the markers named in ``markers_mm``, those flange-frame positions
    (mm, e.g. a fit's) instead of the model's."""
    params = chain.with_offsets(offsets_rad)
    if markers_mm:
        start = chain.marker_slice().start
        for name, xyz in markers_mm.items():
            m = chain.marker_names.index(name)
            params[start + 3 * m: start + 3 * m + 3] = xyz
    pos = chain.marker_positions(data.q_rad, params)
    idx = np.array([chain.marker_names.index(m) for m in data.marker])
    return pos[np.arange(len(data)), idx]


def relative_errors(data: Dataset, p_robot: np.ndarray) -> np.ndarray:
    """Eq. 17 over every pose group with two or more configurations; (n_pairs,) mm."""
    out = []
    groups = {}
    for i, (pose, sensor, marker) in enumerate(zip(data.pose, data.sensor, data.marker)):
        if pose:
            groups.setdefault((pose, sensor, marker), []).append(i)
    for rows in groups.values():
        if len(rows) < 2:
            continue
        r = np.array(rows)
        i, j = np.triu_indices(r.size, k=1)
        d_ref = np.linalg.norm(data.xyz_mm[r[i]] - data.xyz_mm[r[j]], axis=1)
        d_rob = np.linalg.norm(p_robot[r[i]] - p_robot[r[j]], axis=1)
        out.append(np.abs(d_ref - d_rob))
    return np.concatenate(out) if out else np.zeros(0)


def absolute_errors(data: Dataset, p_robot: np.ndarray) -> np.ndarray:
    """Eq. 18 per point after registering ``p_robot`` to the measurements per sensor; (k,) mm."""
    err = np.empty(len(data))
    for s in data.sensors:
        rows = np.flatnonzero(data.sensor == s)
        reg = register_least_squares(p_robot[rows], data.xyz_mm[rows])
        err[rows] = np.linalg.norm(apply(reg.base2sensor, p_robot[rows]) - data.xyz_mm[rows], axis=1)
    return err


def registrations(data: Dataset, p_robot: np.ndarray) -> dict[str, np.ndarray]:
    """Least-squares base2sensor (4, 4) per sensor of ``data`` for the predicted points (k, 3) mm."""
    out = {}
    for s in data.sensors:
        rows = np.flatnonzero(data.sensor == s)
        out[s] = register_least_squares(p_robot[rows], data.xyz_mm[rows]).base2sensor
    return out


def registered_errors(data: Dataset, p_robot: np.ndarray, base2sensor: dict[str, np.ndarray]) -> np.ndarray:
    """|measured − base2sensor · predicted| per row (k,) mm, with the given registration per sensor
    (every sensor of ``data`` must have one)."""
    missing = sorted(set(data.sensors) - set(base2sensor))
    if missing:
        raise ValueError(f"no registration for sensor(s) {missing}; registered: {sorted(base2sensor)}")
    t = np.stack([base2sensor[s] for s in data.sensor])
    pred = np.einsum("kij,kj->ki", t[:, :3, :3], p_robot) + t[:, :3, 3]
    return np.linalg.norm(data.xyz_mm - pred, axis=1)


def validation_scores(cal: Dataset, val: Dataset, before: tuple[np.ndarray, np.ndarray],
                      after: tuple[np.ndarray, np.ndarray], *, registration_after: dict[str, np.ndarray] | None = None,
                      located: dict[str, str] | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Absolute errors of the validation rows, before and after, both scored the same way.

    before / after: (predicted calibration rows (k_cal, 3), predicted validation rows (k_val, 3)) mm.
    Each model is registered on the calibration data (least squares; ``registration_after``: the
    fit's own registration for the after model) and that registration scores the validation rows.
    Returns (before, after) with the calibration registration, (before, after) re-registered on
    the validation rows themselves (optimistic: shown beside, named as such), and caveats: sensors
    the calibration data lack are re-registered in both; markers it lacks were not fitted, unless
    ``located`` (marker → how the after model places it) says how they were located.
    """
    notes = []
    reg_b = registrations(cal, before[0])
    reg_a = dict(registration_after) if registration_after else registrations(cal, after[0])
    foreign = sorted(set(val.sensors) - set(cal.sensors))
    if foreign:
        # No calibration registration exists for them: register on the validation rows, say so.
        reg_b.update({s: r for s, r in registrations(val, before[1]).items() if s in foreign})
        reg_a.update({s: r for s, r in registrations(val, after[1]).items() if s in foreign})
        notes.append(f"validation sensor(s) {', '.join(foreign)} are not in the calibration data: their validation "
                     "points are scored with a registration fitted to those points themselves (optimistic)")
    located = located or {}
    notes += [f"validation marker {m} was not measured in the calibration data: {how}" for m, how in sorted(located.items())]
    unseen = sorted(set(val.marker.tolist()) - set(cal.marker.tolist()) - set(located))
    if unseen:
        notes.append(f"validation marker(s) {', '.join(unseen)} were not measured in the calibration data: their "
                     "position on the flange is the model's, not fitted, so their errors include the tool's error "
                     "(measure them in the calibration, or give their position from a measurement)")
    vb, va = registered_errors(val, before[1], reg_b), registered_errors(val, after[1], reg_a)
    rb, ra = absolute_errors(val, before[1]), absolute_errors(val, after[1])
    return vb, va, rb, ra, notes


def theoretical_errors(
    chain: Chain,
    q_rad: np.ndarray,
    reference_offsets_rad: np.ndarray,
    offset_draws_rad: np.ndarray,
    sigma_mm: float | None,
    *,
    rng: np.random.Generator,
    n_draws: int = 2000,
) -> np.ndarray:
    """Sec. V-C: |TCP(reference) − (TCP(draw) + ε)|, ε ~ N(0, σ² I) (omitted if σ is None).

    q_rad: (k, n) configurations; offset_draws_rad: (m, n) posterior draws (a random subset of
    ``n_draws`` is used). Returns (n_draws · k,) mm.
    """
    pick = rng.choice(offset_draws_rad.shape[0], size=min(n_draws, offset_draws_rad.shape[0]), replace=False)
    draws = offset_draws_rad[pick]
    # The TCP is the flange origin; only the offsets change, so fold the rest of the chain once.
    fk = offset_kinematics(chain, q_rad, np.zeros(3))
    ref = fk.positions(np.asarray(reference_offsets_rad, dtype=float))  # (k, 3)
    out = np.empty((draws.shape[0], q_rad.shape[0]))
    for start in range(0, draws.shape[0], 256):
        block = draws[start : start + 256]
        tcp = fk.positions(block)  # (b, k, 3)
        if sigma_mm is not None:
            tcp = tcp + rng.normal(0.0, sigma_mm, size=tcp.shape)
        out[start : start + block.shape[0]] = np.linalg.norm(tcp - ref, axis=-1)
    return out.ravel()


@dataclass
class TheoreticalDraws:
    """The four theoretical error sets at k configurations, each (d, k) mm: rows are posterior
    draws, columns configurations. Keys ``""`` (with σ) and ``"_offsets_only"``; values (before,
    after). ``draws_se(e)``: the standard error of ``e.mean()`` from the draws (the
    configurations held fixed)."""

    errors: dict[str, tuple[np.ndarray, np.ndarray]]

    @property
    def n_draws(self) -> int:
        return self.errors[""][0].shape[0]

    @staticmethod
    def draws_se(e: np.ndarray) -> float:
        """Std of the per-draw means over √d: the draws are independent, the configurations shared."""
        return float(e.mean(axis=1).std(ddof=1) / np.sqrt(e.shape[0])) if e.shape[0] > 1 else float("inf")

    def worst_draws_sd(self) -> float:
        """The largest std of the per-draw means over the four sets: the spread one draw adds."""
        return max(self.draws_se(e) * np.sqrt(e.shape[0]) for pair in self.errors.values() for e in pair)


def _theoretical_four(
    chain: Chain,
    q_rad: np.ndarray,
    before_rad: np.ndarray,
    after_rad: np.ndarray,
    offset_draws_rad: np.ndarray,
    sigma_mm: float,
    *,
    rng: np.random.Generator,
    n_draws: int,
    mc_se_mm: float | None = None,
    min_draws: int = 100,
) -> TheoreticalDraws:
    """``theoretical_errors`` for both references, with and without σ, from one evaluation of
    the drawn TCPs (the costly part): the same draws and the same ε serve before and after, so the
    before/after pair is compared on common random numbers.

    Posterior draws are taken in a random order without replacement, at most ``n_draws``. With
    ``mc_se_mm`` the draws stop once each of the four means' standard error from the draws
    (``TheoreticalDraws.draws_se``) is at most ``mc_se_mm`` — after ``min_draws``, then as many as
    the spread seen so far says are needed, re-checked; without it all ``n_draws`` are used.
    """
    order = rng.permutation(offset_draws_rad.shape[0])[: min(n_draws, offset_draws_rad.shape[0])]
    fk = offset_kinematics(chain, q_rad, np.zeros(3))
    refs = [fk.positions(np.asarray(r, dtype=float)) for r in (before_rad, after_rad)]  # (k, 3) each
    k = q_rad.shape[0]
    out = {key: (np.empty((order.size, k)), np.empty((order.size, k))) for key in ("", "_offsets_only")}
    done = 0
    want = order.size if mc_se_mm is None else min(min_draws, order.size)
    while done < want:
        for start in range(done, want, 256):
            block = slice(start, min(start + 256, want))
            tcp = np.moveaxis(fk.positions(offset_draws_rad[order[block]]), -1, 0)  # (3, b, k)
            noisy = tcp + rng.normal(0.0, sigma_mm, size=tcp.shape)
            for key, pts in (("", noisy), ("_offsets_only", tcp)):
                for side, ref in zip(out[key], refs):
                    dx, dy, dz = pts[0] - ref[:, 0], pts[1] - ref[:, 1], pts[2] - ref[:, 2]
                    side[block] = np.sqrt(dx * dx + dy * dy + dz * dz)  # |·| without norm's generic reduction
        done = want
        if mc_se_mm is not None:
            sd = TheoreticalDraws({key: (b[:done], a[:done]) for key, (b, a) in out.items()}).worst_draws_sd()
            need = (sd / mc_se_mm) ** 2  # infinite from a single draw: take all there are
            want = order.size if not np.isfinite(need) else min(order.size, max(done, int(np.ceil(need))))
    return TheoreticalDraws({key: (b[:done], a[:done]) for key, (b, a) in out.items()})


def _mc_se(e: np.ndarray, *, random_configurations: bool) -> float:
    """Standard error of ``e.mean()`` for errors (d draws, k configurations): from the draws, plus
    for a random sample of configurations the spread of the per-configuration means over √k."""
    se = TheoreticalDraws.draws_se(e)
    if random_configurations and e.shape[1] > 1:
        se = float(np.hypot(se, e.mean(axis=0).std(ddof=1) / np.sqrt(e.shape[1])))
    return se


def random_configurations(chain: Chain, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` joint vectors uniformly within the model's limits, (n, n_joints) rad."""
    m = chain.model
    return rng.uniform(m.lower_limits_rad, m.upper_limits_rad, size=(n, m.n_joints))


def before_after(chain: Chain, data: Dataset, offsets_rad: np.ndarray) -> dict[str, dict]:
    """Relative and absolute metrics with nominal (before) and fitted (after) offsets."""
    before = predicted_base(chain, data, np.zeros(chain.n))
    after = predicted_base(chain, data, offsets_rad)
    out = {}
    rel_b, rel_a = relative_errors(data, before), relative_errors(data, after)
    if rel_b.size:
        out["relative"] = {"before": summarize(rel_b).to_dict(), "after": summarize(rel_a).to_dict()}
    out["absolute"] = {
        "before": summarize(absolute_errors(data, before)).to_dict(),
        "after": summarize(absolute_errors(data, after)).to_dict(),
    }
    return out


def _pair(before: np.ndarray, after: np.ndarray) -> dict:
    return {"before": summarize(before).to_dict(), "after": summarize(after).to_dict()}


#: At most this many posterior draws per configuration for the theoretical metrics (the default
#: fit has 4 × 1000 draws, ~1000–1600 of them effective).
THEORETICAL_DRAWS = 1000

#: The precision the theoretical means are computed to: draws are added until the standard error
#: each mean owes to the draws is at most this (mm) — the last decimal the terminal summary prints.
#: The iiwa example (180 measured, 1000 random configurations) stops at ~600 draws for the
#: measured configurations (their errors with σ need the most) and ~120 for the workspace, a
#: fifth of the evaluations of 1000 each. The 2.5 / 97.5 % points move 2–4 times as much as
#: the means between seeds; the max is a sample extreme (it grows with the count ``n``).
MC_SE_MM = 0.001


def accuracy_metrics(
    chain: Chain,
    data: Dataset,
    applied_offsets_rad: np.ndarray,
    offset_draws_rad: np.ndarray,
    sigma_mm: float,
    *,
    validation: Dataset | None = None,
    markers_mm: dict[str, np.ndarray] | None = None,
    before_markers_mm: dict[str, np.ndarray] | None = None,
    n_random: int = 1000,
    n_draws: int = THEORETICAL_DRAWS,
    mc_se_mm: float | None = MC_SE_MM,
    seed: int = 0,
) -> dict:
    """Every metric of the paper's Sec. V–VI, before (nominal offsets) and after (applied ones).

    applied_offsets_rad: (n,) the offsets that would be entered (0 where left unchanged);
    offset_draws_rad: (m, n) posterior draws; sigma_mm: the isotropic error scale.
    Returns a dict of metric name → {"before": Summary dict, "after": Summary dict} (mm):

    ``relative`` (eq. 17, Table III; only with pose groups), ``absolute`` (eq. 18, Table IV),
    ``theoretical_measured`` (Table V: offsets draws + σ at the measured configurations),
    ``theoretical_measured_offsets_only`` (the same without σ), ``theoretical_workspace``
    (Table VI: ``n_random`` uniform configurations within the joint limits),
    ``theoretical_workspace_offsets_only`` (Table VII), and with ``validation`` the
    ``validation_relative`` / ``validation_absolute`` of Table VIII — the latter scored with the
    registration of the calibration data (``validation_scores``), with the optimistic
    ``validation_absolute_reregistered`` beside it. ``markers_mm``: fitted marker positions
    (flange frame, mm) that belong to the "after" model; ``before_markers_mm``: those of the robot as
    found (zero offsets, its tool fitted: ``calib.fit.entered.as_found_markers``; None: the model's
    drawing, a before nobody has). ``notes``: caveats. Plus ``offsets_share``:
    mean error from the offsets alone ÷ mean error with σ, over the workspace (the paper's
    "95 % before, 15 % after"), and ``settings`` (n_random, n_draws, σ, seed).

    The theoretical metrics are Monte-Carlo estimates: at most ``n_draws`` posterior draws per
    configuration, fewer once every mean's standard error from the draws is at most ``mc_se_mm``
    (None: all ``n_draws``; ``_theoretical_four``). Each of their summaries carries ``mc_se``, the
    standard error of its mean: from the draws at the measured configurations (a fixed set), from
    the draws and the random configurations together over the workspace. ``settings`` gives the
    draws used per configuration (``draws_measured``, ``draws_workspace``) and ``mc_se_target_mm``.
    """
    rng = np.random.default_rng(seed)
    zero = np.zeros(chain.n)
    applied = np.asarray(applied_offsets_rad, dtype=float)
    out: dict = {}
    before = predicted_base(chain, data, zero, markers_mm=before_markers_mm)
    after = predicted_base(chain, data, applied, markers_mm=markers_mm)
    rel_b, rel_a = relative_errors(data, before), relative_errors(data, after)
    if rel_b.size:
        out["relative"] = _pair(rel_b, rel_a)
    out["absolute"] = _pair(absolute_errors(data, before), absolute_errors(data, after))
    q_meas = np.unique(data.q_rad, axis=0)
    q_rand = random_configurations(chain, n_random, rng)
    used = {}
    for where, q in (("measured", q_meas), ("workspace", q_rand)):
        four = _theoretical_four(chain, q, zero, applied, offset_draws_rad, sigma_mm, rng=rng, n_draws=n_draws,
                                 mc_se_mm=mc_se_mm)
        used[where] = four.n_draws
        for suffix, pair in four.errors.items():
            out[f"theoretical_{where}{suffix}"] = {
                when: summarize(e, _mc_se(e, random_configurations=where == "workspace")).to_dict()
                for when, e in zip(("before", "after"), pair)}
    ws, wo = out["theoretical_workspace"], out["theoretical_workspace_offsets_only"]
    out["offsets_share"] = {k: (wo[k]["mean"] / ws[k]["mean"] if ws[k]["mean"] > 0 else float("nan")) for k in ("before", "after")}
    if validation is not None and len(validation):
        vb = predicted_base(chain, validation, zero, markers_mm=before_markers_mm)
        va = predicted_base(chain, validation, applied, markers_mm=markers_mm)
        vrel_b, vrel_a = relative_errors(validation, vb), relative_errors(validation, va)
        if vrel_b.size:
            out["validation_relative"] = _pair(vrel_b, vrel_a)
        # The headline scores only markers the calibration measured; the others (their position the
        # model's, not fitted) apart, named as such.
        seen = np.isin(validation.marker, data.marker)
        notes = []
        if seen.any():
            v = validation.subset(seen)
            eb, ea, rb, ra, notes = validation_scores(data, v, (before, vb[seen]), (after, va[seen]))
            out["validation_absolute"] = _pair(eb, ea)
            out["validation_absolute_reregistered"] = _pair(rb, ra)
        if not seen.all():
            v = validation.subset(~seen)
            eb, ea, _, _, more = validation_scores(data, v, (before, vb[~seen]), (after, va[~seen]))
            out["validation_absolute_unseen_markers"] = _pair(eb, ea)
            notes += more + ["validation_absolute_unseen_markers: validation points of markers the calibration never "
                             "measured, apart from the headline (their position on the flange is the model's)"]
        out["notes"] = notes + ["validation_absolute: the validation points scored with the registration of the "
                                "calibration data; validation_absolute_reregistered: with one fitted to the validation "
                                "points themselves (absorbs part of their error: optimistic)"]
    out["settings"] = {
        "n_random_configurations": int(n_random),
        "n_measured_configurations": int(q_meas.shape[0]),
        "n_draws": int(min(n_draws, offset_draws_rad.shape[0])),
        "draws_measured": used["measured"],
        "draws_workspace": used["workspace"],
        "mc_se_target_mm": mc_se_mm,
        "sigma_mm": float(sigma_mm),
        "seed": int(seed),
        "tcp": "flange origin",
    }
    return out
