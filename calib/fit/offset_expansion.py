"""Marker positions as a low-order polynomial of the fitted parameters about the posterior mode.

The fast sampler evaluates the posterior at thousands of proposals, all within a few posterior
standard deviations of the mode: offsets within ~1e-3 rad of it, tool coordinates within a
fraction of a millimetre, link deviations of tenths of a millimetre. About a reference point —
offsets δ*, the nominal links, marker positions m* on the flange — each row's marker in the
robot base frame is, with ε = δ − δ*, Δm = m − m* and link deviations λ,

    p = p* + Σ_i J_i ε_i + ½ Σ_ij H_ij ε_i ε_j + R* Δm + Σ_i ε_i (w_i × R* Δm) + J_λ λ

where w_i = sign_i·ω_i is joint i's axis (base frame, at the reference), J_i = w_i × (p* − o_i)
and, for i ≤ j, H_ij = w_i × J_j (a turn about axis i carries axis j and everything after it);
R* is the flange rotation. Evaluating it is one matrix product per batch of proposals instead of
a walk of the chain. The first neglected terms are third order in ε (≈ |p − o|·|ε|³, 1e-6 mm at
a 1 m lever and ε = 1e-3 rad), second order in ε times Δm, and — as in
``OffsetPosterior.linearise_links`` — products of λ with ε or λ.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.robot.kinematics import Chain
from calib.robot.transforms import cross


#: The expanded predictor (``calib.fit.posterior.OffsetPosterior.expand``, and the attitude rows' flange rotations) must agree with the chain walk it stands for
#: to this (mm) at the proposals farthest from the mode, or the batch is walked instead: the
#: accuracy of the link terms' own first-order form, 1/1000 of a typical σ.
EXPANSION_TOLERANCE_MM = 1e-4


@dataclass(frozen=True)
class OffsetExpansion:
    """The polynomial above for k rows, with F = f + f(f+1)/2 + Λ + T + f·T terms.

    reference: (3k,) p* mm; coeff: (F, 3k) mm per unit of each term; pairs: (2, f(f+1)/2) the
    (i, j), i ≤ j, of the quadratic terms; f offsets, Λ link parameters, T tool coordinates.
    """

    reference: np.ndarray
    coeff: np.ndarray
    pairs: np.ndarray
    n_offsets: int
    n_links: int
    n_tool: int

    @property
    def n_rows(self) -> int:
        return self.reference.size // 3

    def positions(self, d_offsets: np.ndarray, d_links: np.ndarray, d_tool: np.ndarray) -> np.ndarray:
        """Markers (b, k, 3) mm for deviations from the reference, each (b, ·): offsets ε rad (f),
        link deviations λ (Λ, mm or rad), tool coordinates Δm mm (T)."""
        eps = np.atleast_2d(d_offsets)
        b = eps.shape[0]
        terms = [eps, eps[:, self.pairs[0]] * eps[:, self.pairs[1]], np.atleast_2d(d_links).reshape(b, self.n_links)]
        if self.n_tool:
            tool = np.atleast_2d(d_tool)
            terms += [tool, (eps[:, :, None] * tool[:, None, :]).reshape(b, -1)]
        phi = np.concatenate(terms, axis=1)  # (b, F)
        return (self.reference + phi @ self.coeff).reshape(b, self.n_rows, 3)


def expand_offsets(chain: Chain, q: np.ndarray, marker_index: np.ndarray, params: np.ndarray, offsets: np.ndarray,
                   links: np.ndarray, tool: np.ndarray) -> OffsetExpansion:
    """The expansion about ``params`` (P,) at configurations q (k, n) rad, row k measuring marker
    ``marker_index[k]``. ``offsets``: joint indices (f,) expanded to second order (ascending);
    ``links``: chain parameter indices (Λ,) taken to first order; ``tool``: chain parameter
    indices (T,) of marker coordinates (``Chain.marker_slice``)."""
    offsets = np.asarray(offsets, dtype=int)
    if np.any(np.diff(offsets) <= 0):
        raise ValueError(f"offsets must be ascending joint indices, given {offsets}")
    k = q.shape[0]
    rows = np.arange(k)
    fj = chain.flange_jacobian(q, params)  # its jw: the axes sign_i ω_i
    pos, jac = chain.marker_jacobian(q, params)
    p_ref = pos[rows, marker_index]  # (k, 3)
    j_rows = jac[rows, marker_index]  # (k, 3, P)
    w = np.moveaxis(fj.jw[:, :, offsets], -1, 0)  # (f, k, 3): sign_i ω_i
    j_off = np.moveaxis(j_rows[:, :, offsets], -1, 0)  # (f, k, 3)
    f = offsets.size
    ii, jj = np.triu_indices(f)
    quad = cross(w[ii], j_off[jj]) * np.where(ii == jj, 0.5, 1.0)[:, None, None]
    terms = [j_off, quad, np.moveaxis(j_rows[:, :, np.asarray(links, dtype=int)], -1, 0)]
    tool = np.asarray(tool, dtype=int)
    if tool.size:
        lin = np.moveaxis(j_rows[:, :, tool], -1, 0)  # (T, k, 3): the flange rotation's columns on the row's marker
        bilinear = cross(w[:, None], lin[None])  # (f, T, k, 3): ε_i Δm_t
        terms += [lin, bilinear.reshape(f * tool.size, k, 3)]
    coeff = np.concatenate(terms, axis=0).reshape(-1, 3 * k)
    return OffsetExpansion(reference=p_ref.reshape(-1), coeff=np.ascontiguousarray(coeff), pairs=np.stack([ii, jj]),
                           n_offsets=f, n_links=len(links), n_tool=tool.size)
