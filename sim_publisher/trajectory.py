"""The office tour: one continuous trajectory, sampled at different step lengths.

The path runs through door centres from the bottom-right room, up the corridor, through the
second west room and ends in the top-left room next to the round pillar (map-frame metres). It
is a corner-cut (Chaikin) smoothing of hand-placed waypoints, parameterised by arc length ``s``.
The heading is the path tangent plus a smooth oscillation ``A sin(k s)``; ``A`` and ``k`` are
chosen so that sampling every ~11 mm gives a mean absolute rotation per step of ~4.0 deg and
every ~104 mm gives ~30.6 deg, as in the paper's two setups.

Odometry integrates the true per-step motion (in the robot frame) with a seeded, realistic
error: a constant translational scale error, per-step translational noise, a constant
rotational drift per metre and per-step rotational noise. It starts at the true first pose.

:class:`Tour` is the same construction for any route (generated buildings use it): control
points -> Chaikin corner cut -> arc-length resampling -> tangent + oscillation, with
:meth:`Tour.calibrated` fitting the oscillation so that both setups' mean rotation per step
match the paper on that route.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from service.core import numeric
from service.core.types import wrap_angle

# Waypoints (m). Pairs of points straddle each door so the smoothed path crosses it squarely.
TOUR_WAYPOINTS = np.array(
    [
        [9.4, 1.95],  # start, bottom-right room
        [12.3, 1.5],
        [12.7, 4.6],
        [11.0, 6.5],
        [9.3, 5.7],
        [8.4, 4.0],
        [7.0, 4.0],  # through east door (7.6, 4.0)
        [6.6, 4.6],
        [6.6, 7.0],
        [6.2, 7.6],
        [4.8, 7.6],  # through west door (5.6, 7.6)
        [3.3, 6.95],
        [1.5, 7.9],
        [1.55, 9.8],
        [3.2, 10.6],
        [4.8, 10.6],
        [6.2, 10.6],  # through west door (5.6, 10.6)
        [6.6, 11.2],
        [6.6, 19.2],
        [6.2, 19.8],
        [4.8, 19.8],  # through west door (5.6, 19.8)
        [3.6, 20.4],
        [2.7, 21.3],
        [2.2, 20.2],
        [2.6, 19.0],
    ]
)

# Heading oscillation (amplitude rad, wavenumber rad/m) and the two sampling steps (m).
OSC_AMPLITUDE = np.deg2rad(27.5)
OSC_WAVENUMBER = 20.7
STEP_SETUP1 = 0.011
STEP_SETUP2 = 0.104
# The paper's mean rotation per step of the two setups (rad).
TURN_SETUP1 = float(np.deg2rad(4.0))
TURN_SETUP2 = float(np.deg2rad(30.6))
_DENSE_DS = 0.002  # resolution of the stored continuous path (m)


@dataclass(frozen=True)
class OdometryNoise:
    """Odometry error model.

    ``scale_error``: relative translational scale bias (sign drawn per run). ``trans_noise``:
    relative per-step translational noise (std). ``drift``: rotational bias in rad per metre
    travelled (sign drawn per run). ``rot_noise``: per-step rotational noise, rad per
    sqrt(m) travelled. ``rot_rel_noise``: per-step rotational noise relative to the turned
    angle (std).
    """

    scale_error: float = 0.03
    trans_noise: float = 0.02
    drift: float = float(np.deg2rad(1.0))
    rot_noise: float = float(np.deg2rad(0.5))
    rot_rel_noise: float = 0.02


def chaikin(points: np.ndarray, iterations: int = 5) -> np.ndarray:
    """Corner-cutting smoothing of an open polyline ``(k, 2)``; keeps both end points."""
    p = np.asarray(points, dtype=np.float64)
    for _ in range(iterations):
        q = 0.75 * p[:-1] + 0.25 * p[1:]
        r = 0.25 * p[:-1] + 0.75 * p[1:]
        mid = np.empty((2 * len(q), 2))
        mid[0::2] = q
        mid[1::2] = r
        p = np.vstack([p[:1], mid[1:-1], p[-1:]])
    return p


def dense_path(
    control: np.ndarray, iterations: int = 6
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Arc length ``s`` (m), positions ``(m, 2)`` and unwrapped tangent angle (rad) of the
    Chaikin-smoothed polyline through ``control`` points, resampled every ``_DENSE_DS``."""
    poly = chaikin(control, iterations)
    seg = np.hypot(*np.diff(poly, axis=0).T)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    s = np.arange(0.0, cum[-1], _DENSE_DS)
    xy = np.c_[np.interp(s, cum, poly[:, 0]), np.interp(s, cum, poly[:, 1])]
    d = np.gradient(xy, axis=0)
    tangent = np.unwrap(numeric.atan2(d[:, 1], d[:, 0]))
    # Light smoothing of the tangent (Gaussian, sigma 2 cm) removes the chord kinks.
    k = numeric.exp(-0.5 * (np.arange(-30, 31) * _DENSE_DS / 0.02) ** 2)
    k /= k.sum()
    padded = np.concatenate([np.full(30, tangent[0]), tangent, np.full(30, tangent[-1])])
    # np.convolve would sum through BLAS, whose kernels (and so the last bits) differ by CPU
    windows = np.lib.stride_tricks.sliding_window_view(padded, len(k))
    tangent = np.einsum("ij,j->i", windows, k[::-1])
    for arr in (s, xy, tangent):
        arr.setflags(write=False)
    return s, xy, tangent


@dataclass(frozen=True)
class Tour:
    """One continuous tour (map frame): arc length ``s`` (m, every ``_DENSE_DS``), positions
    ``xy`` (m), unwrapped path tangent (rad) and the heading oscillation ``amplitude`` (rad)
    x ``sin(wavenumber (rad/m) * s)`` added to the tangent."""

    s: np.ndarray
    xy: np.ndarray
    tangent: np.ndarray
    amplitude: float = float(OSC_AMPLITUDE)
    wavenumber: float = OSC_WAVENUMBER

    @staticmethod
    def from_control_points(control: np.ndarray, iterations: int = 6) -> Tour:
        """The smoothed tour through ``control`` points ``(k, 2)`` (office oscillation)."""
        s, xy, tangent = dense_path(np.asarray(control, dtype=np.float64), iterations)
        return Tour(s, xy, tangent)

    @property
    def length(self) -> float:
        """Length (m)."""
        return float(self.s[-1])

    def arc(self, step: float, max_scans: int | None = None) -> np.ndarray:
        """Arc lengths (m) of the samples taken every ``step`` m (optionally the first
        ``max_scans``)."""
        s = np.arange(0.0, self.s[-1], step)
        if max_scans is not None:
            s = s[: max(int(max_scans), 0)]
        return s

    def poses(self, step: float, max_scans: int | None = None) -> np.ndarray:
        """True poses ``(n, 3)`` every ``step`` m of arc length; heading = tangent +
        ``amplitude * sin(wavenumber * s)`` wrapped to (-pi, pi]."""
        return self.poses_at(self.arc(step, max_scans))

    def poses_at(self, s: np.ndarray) -> np.ndarray:
        """Poses ``(n, 3)`` at arc lengths ``s`` (m)."""
        x = np.interp(s, self.s, self.xy[:, 0])
        y = np.interp(s, self.s, self.xy[:, 1])
        th = np.interp(s, self.s, self.tangent) + self.amplitude * np.sin(self.wavenumber * s)
        return np.c_[x, y, wrap_angle(th)]

    def truncated(self, length: float) -> Tour:
        """The first ``length`` m of the tour."""
        n = int(np.searchsorted(self.s, length, side="right"))
        return replace(self, s=self.s[:n], xy=self.xy[:n], tangent=self.tangent[:n])

    def calibrated(
        self,
        targets: tuple[tuple[float, float], ...] = (
            (STEP_SETUP1, TURN_SETUP1),
            (STEP_SETUP2, TURN_SETUP2),
        ),
    ) -> Tour:
        """The tour with ``amplitude`` and ``wavenumber`` fitted (least squares on relative
        errors) so that sampling every ``step`` m gives a mean absolute rotation per step of
        ``turn`` rad, for each ``(step, turn)`` of ``targets``; starts from the office's."""

        def resid(p: np.ndarray) -> np.ndarray:
            t = replace(self, amplitude=float(p[0]), wavenumber=float(p[1]))
            out = []
            for step, turn in targets:
                th = t.poses(step)[:, 2]
                out.append(np.abs(wrap_angle(np.diff(th))).mean() / turn - 1.0)
            return np.asarray(out)

        x = fit_bounded(
            resid,
            np.array([OSC_AMPLITUDE, OSC_WAVENUMBER]),
            np.array([0.0, 5.0]),
            np.array([np.deg2rad(60.0), 40.0]),
        )
        return replace(self, amplitude=float(x[0]), wavenumber=float(x[1]))


def fit_bounded(
    resid: Callable[[np.ndarray], np.ndarray],
    x0: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    max_evals: int = 60,
) -> np.ndarray:
    """Parameters within bounds that make ``resid`` small (least squares): Nelder-Mead on the
    sum of squares from a simplex of 5 % steps around ``x0``, at most ``max_evals``
    evaluations.

    Why not scipy's ``least_squares``, used before: its linear algebra runs on OpenBLAS, whose
    kernels differ between CPUs, and the fitted oscillation (so every generated building's
    tour and scans) came out different in the last bits on different machines. Nelder-Mead
    needs no linear algebra, and the mean of |turns| has kinks that it steps over: with the
    same 60 evaluations it fits the turn statistics at least as closely (largest relative
    error over buildings 3, 65, 1000, 1003, 1007, 1011 and 1019: 0.0002-0.0094, against
    0.0009-0.0056 for least squares and 0.004-0.05 for Gauss-Newton on 1 % differences)."""
    from scipy.optimize import minimize

    x0 = np.clip(np.asarray(x0, dtype=np.float64), lo, hi)
    simplex = np.vstack([x0, x0 + np.diag(0.05 * np.maximum(np.abs(x0), 1e-3))])
    res = minimize(
        lambda p: float(np.sum(resid(p) ** 2)),
        x0,
        method="Nelder-Mead",
        bounds=list(zip(lo, hi, strict=True)),
        options={"maxfev": max_evals, "xatol": 1e-4, "fatol": 1e-10, "initial_simplex": simplex},
    )
    return np.clip(np.asarray(res.x, dtype=np.float64), lo, hi)


@lru_cache(maxsize=1)
def office_tour() -> Tour:
    """The office tour (``TOUR_WAYPOINTS``, 6 Chaikin iterations, office oscillation)."""
    return Tour.from_control_points(TOUR_WAYPOINTS, 6)


def tour_length() -> float:
    """Length (m) of the smoothed office tour."""
    return office_tour().length


def tour_poses(step: float, max_scans: int | None = None) -> np.ndarray:
    """True poses ``(n, 3)`` sampled every ``step`` metres of arc length along the office tour.

    Heading = tangent + ``OSC_AMPLITUDE * sin(OSC_WAVENUMBER * s)``, wrapped to (-pi, pi].
    """
    return office_tour().poses(step, max_scans)


def relative_motion(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Motion ``(n, 3)`` from poses ``a`` to ``b`` expressed in the frame of ``a``."""
    dxy = b[:, :2] - a[:, :2]
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.c_[
        c * dxy[:, 0] + s * dxy[:, 1], -s * dxy[:, 0] + c * dxy[:, 1], wrap_angle(b[:, 2] - a[:, 2])
    ]


def simulate_odometry(
    truth: np.ndarray, seed: int, noise: OdometryNoise | None = None
) -> np.ndarray:
    """Drifting odometry poses ``(n, 3)`` for the true poses, starting at ``truth[0]``.

    Deterministic for a given ``(truth, seed, noise)``.
    """
    nz = noise or OdometryNoise()
    truth = np.asarray(truth, dtype=np.float64)
    n = truth.shape[0]
    out = np.empty((n, 3))
    if n == 0:
        return out
    out[0] = truth[0]
    if n == 1:
        return out
    rng = np.random.default_rng((int(seed), 7))
    rel = relative_motion(truth[:-1], truth[1:])
    dist = np.hypot(rel[:, 0], rel[:, 1])
    signs = rng.choice([-1.0, 1.0], size=2)
    scale = 1.0 + signs[0] * nz.scale_error
    drift = signs[1] * nz.drift
    tn = rng.normal(0.0, nz.trans_noise, size=(n - 1, 2))
    rn = rng.normal(0.0, 1.0, size=(n - 1, 2))
    mx = rel[:, 0] * scale * (1.0 + tn[:, 0])
    my = rel[:, 1] * scale * (1.0 + tn[:, 1])
    mth = (
        rel[:, 2] * (1.0 + nz.rot_rel_noise * rn[:, 1])
        + drift * dist
        + nz.rot_noise * np.sqrt(dist) * rn[:, 0]
    )
    x, y, th = truth[0]
    for i in range(n - 1):
        c, s = np.cos(th), np.sin(th)
        x += c * mx[i] - s * my[i]
        y += s * mx[i] + c * my[i]
        th = float(wrap_angle(th + mth[i]))
        out[i + 1] = (x, y, th)
    return out


def run_stats(truth: np.ndarray) -> dict[str, float]:
    """Path length (m), mean step (mm) and mean absolute rotation per step (deg) of a pose
    sequence ``(n, 3)``."""
    t = np.asarray(truth, dtype=np.float64)
    if t.shape[0] < 2:
        return {"path_length_m": 0.0, "mean_step_mm": 0.0, "mean_rotation_deg": 0.0}
    steps = np.hypot(*np.diff(t[:, :2], axis=0).T)
    rot = np.abs(wrap_angle(np.diff(t[:, 2])))
    return {
        "path_length_m": float(steps.sum()),
        "mean_step_mm": float(steps.mean() * 1000.0),
        "mean_rotation_deg": float(np.rad2deg(rot.mean())),
    }
