"""The numerical core of ``gtforge.core.alignment.edge_alignment``'s estimator: the captures' edges as one problem in
pixel units (``_Problem``), the one-pixel quadratic model of the score, the cluster-robust sandwich covariance and the
maximiser (Nelder-Mead, then Newton steps), and the significance of a correction. Private to edge_alignment (its
module docstring says how they fit together)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gtforge.core.camera import PinholeCamera
from gtforge.core.alignment.edge_features import DepthEdges, edge_scores, edge_strength, perturb


@dataclass
class _Cap:
    name: str
    edges: DepthEdges
    undistorted: np.ndarray
    strengths: dict = field(default_factory=dict)

    def strength(self, blur: float):
        if blur not in self.strengths:
            self.strengths[blur] = edge_strength(self.undistorted, blur)
        return self.strengths[blur]


@dataclass
class _Problem:
    """The captures' edges; ``theta`` (6,) the perturbation in pixel units (``scale``)."""

    caps: list[_Cap]
    pinhole: PinholeCamera
    T_color_from_depth_initial: np.ndarray
    scale: np.ndarray  # (6,) theta * scale = (omega rad, delta_t mm)

    @property
    def structure(self) -> np.ndarray:
        out, shift = [], 0
        for c in self.caps:
            out.append(c.edges.structure + shift)
            shift += int(c.edges.structure.max()) + 1 if len(c.edges) else 0
        return np.concatenate(out)

    def pose(self, theta: np.ndarray) -> np.ndarray:
        p = np.asarray(theta, float) * self.scale
        return perturb(self.T_color_from_depth_initial, p[:3], p[3:])

    def scores(self, theta: np.ndarray, blur: float) -> np.ndarray:
        T_color_from_depth = self.pose(theta)
        return np.concatenate([edge_scores(c.edges, T_color_from_depth, self.pinhole, c.strength(blur))
                               for c in self.caps])


def _quadratic_model(f, theta: np.ndarray, step_px: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Gradient and Hessian of ``f`` (a scalar, or a vector per edge for the gradient) by central differences
    one pixel wide, on purpose: the score is a mean of bilinear samples, kinked at every pixel and flat-topped
    where structures disagree by a pixel or two, and ``tests/io/test_real_frame.py`` locates its peak the same way
    (a parabola through the maximum and its neighbours one pixel away). An adaptive differentiation
    (``scipy.differentiate``) would chase the kinks."""
    n, h = len(theta), step_px
    E = np.eye(n) * h
    f0 = f(theta)
    fp = [f(theta + E[k]) for k in range(n)]
    fm = [f(theta - E[k]) for k in range(n)]
    grad = np.stack([(fp[k] - fm[k]) / (2 * h) for k in range(n)], axis=-1)
    H = np.zeros((n, n) + np.shape(f0))
    for k in range(n):
        H[k, k] = (fp[k] - 2 * f0 + fm[k]) / h**2
        for m in range(k):
            H[k, m] = H[m, k] = (f(theta + E[k] + E[m]) - f(theta + E[k] - E[m]) - f(theta - E[k] + E[m])
                                 + f(theta - E[k] - E[m])) / (4 * h**2)
    return grad, H


def _restrict(f, theta: np.ndarray, idx: np.ndarray):
    def g(t):
        full = theta.copy()
        full[idx] = t
        return f(full)
    return g


def _sandwich(problem: _Problem, theta: np.ndarray, blur: float, free: np.ndarray) -> np.ndarray:
    """Covariance (pixel units, 6x6, inf outside ``free``) of the score maximiser over the ``free`` parameters,
    the others held: the cluster-robust sandwich ``H^-1 B H^-1`` of an M-estimator. ``H`` is the Hessian of the
    summed score; ``B`` sums, over the connected edge structures (one contour each: its samples see the same colour
    edge and share its offset, so a contour is one observation, not hundreds), the outer product of the
    structure's summed per-edge score gradient. Structures that disagree (a table edge whose colour transition
    lies 3 px below its depth silhouette beside a window sill that matches) make the variance large. A direction
    in which the score does not curve down (``H`` not negative definite) gets an infinite variance."""
    idx = np.flatnonzero(free)
    per_edge = _restrict(lambda t: problem.scores(t, blur), theta, idx)
    J, _ = _quadratic_model(per_edge, theta[idx])
    _, H = _quadratic_model(lambda t: per_edge(t).sum(), theta[idx])
    _, label = np.unique(problem.structure, return_inverse=True)
    G = np.zeros((label.max() + 1, len(idx)))
    np.add.at(G, label, J)
    n_clusters = len(G)
    B = G.T @ G * n_clusters / max(n_clusters - 1, 1)  # the usual small-sample factor
    w, V = np.linalg.eigh(-H)  # a maximum: -H positive definite
    good = w > 1e-6 * max(w.max(), 1e-30)
    Hinv = (V[:, good] / w[good]) @ V[:, good].T
    cov = Hinv @ B @ Hinv
    undetermined = (np.abs(V[:, ~good]) > 0.05).any(axis=1)  # loads on a direction without curvature
    cov[undetermined, :] = np.inf
    cov[:, undetermined] = np.inf
    full = np.full((6, 6), np.inf)
    full[np.ix_(idx, idx)] = cov
    return full


def _maximise(problem: _Problem, blur: float, theta0: np.ndarray, free: np.ndarray, polish: bool) -> np.ndarray:
    """Nelder-Mead on the mean score over the ``free`` parameters (1 px initial steps); with ``polish``, then
    Newton steps on the one-pixel quadratic model (``_quadratic_model``), which find the centre of a flat top where
    Nelder-Mead stops anywhere on it."""
    from scipy.optimize import minimize  # here, not at import: importing scipy slows every process start

    idx = np.flatnonzero(free)
    score = _restrict(lambda t: problem.scores(t, blur).mean(), theta0, idx)
    simplex = theta0[idx] + np.vstack([np.zeros(len(idx)), np.eye(len(idx))])
    t = minimize(lambda t: -score(t), theta0[idx], method="Nelder-Mead",
                 options=dict(initial_simplex=simplex, xatol=0.005, fatol=1e-7, maxiter=4000)).x
    for _ in range(10 if polish else 0):
        g, H = _quadratic_model(score, t)
        w = np.linalg.eigvalsh(H)
        if w.max() >= 0:  # not a maximum of the quadratic model: keep Nelder-Mead's point
            break
        step = -np.linalg.solve(H, g)
        if np.abs(step).max() > 1.0:  # beyond the pixel the model describes
            break
        t = t + step
        if np.abs(step).max() < 0.005:
            break
    out = theta0.copy()
    out[idx] = t
    return out


def _significance_sigma(x: np.ndarray, cov: np.ndarray) -> float:
    """``x`` against 0 with covariance ``cov``: the chi-square's tail as a two-sided normal sigma."""
    from scipy.stats import chi2, norm  # here, not at import: importing scipy slows every process start

    q = float(x @ np.linalg.solve(cov, x))
    p = chi2.sf(q, len(x)) if q > 0 else 1.0
    return float(norm.isf(0.5 * p)) if p > 1e-300 else float(np.sqrt(q))  # (far out in the tail: about sqrt(q))
