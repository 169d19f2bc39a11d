"""A careful nlopt driver: one call, checked results, the project's own errors.

nlopt is used as is, with three traps handled here (see ``shared/reference/libraries.md``):
the gradient must be written in place; several algorithms (SLSQP, MMA, BOBYQA, CRS2,
...) return a *success* code with a NaN objective, so every result is checked for
finiteness here and the best finite point seen is kept; and nlopt's exceptions carry empty
messages, so they are turned into :class:`~gonio.errors.FitError` with the algorithm
named, or, when a finite point was reached before the failure, into a non-success status
with that point.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import nlopt
import numpy as np

from gonio.errors import FitError, GonioError, UnknownNameError

__all__ = [
    "ALGORITHMS",
    "GLOBAL_ALGORITHMS",
    "LOCAL_ALGORITHMS",
    "NloptResult",
    "nlopt_minimize",
    "sobol_design",
]

LOCAL_ALGORITHMS = (
    "LD_LBFGS",
    "LD_SLSQP",
    "LD_MMA",
    "LD_CCSAQ",
    "LN_BOBYQA",
    "LN_SBPLX",
    "LN_NELDERMEAD",
    "LN_COBYLA",
)
GLOBAL_ALGORITHMS = ("GN_DIRECT_L", "GN_CRS2_LM", "G_MLSL_LDS", "GN_ISRES")
ALGORITHMS = LOCAL_ALGORITHMS + GLOBAL_ALGORITHMS

_MESSAGES = {
    1: "success",
    2: "stopval reached",
    3: "ftol reached",
    4: "xtol reached",
    5: "maxeval reached",
    6: "maxtime reached",
    -1: "generic failure",
    -2: "invalid arguments",
    -3: "out of memory",
    -4: "roundoff limited",
    -5: "forced stop",
}


@dataclass
class NloptResult:
    """Outcome of :func:`nlopt_minimize`: best finite point, its cost, status, counts."""

    x: np.ndarray
    fun: float
    status: int
    message: str
    nfev: int
    algorithm: str

    @property
    def success(self) -> bool:
        return self.status > 0 and bool(np.isfinite(self.fun)) and bool(np.all(np.isfinite(self.x)))


def _algorithm(name: str) -> int:
    code = getattr(nlopt, name, None) if name.isupper() else None
    if not isinstance(code, int) or name not in ALGORITHMS:
        raise UnknownNameError(
            f"unknown nlopt algorithm {name!r}; expected one of {', '.join(ALGORITHMS)}"
        )
    return code


def nlopt_minimize(
    fun: Callable[[np.ndarray, bool], tuple[float, np.ndarray]],
    x0: np.ndarray,
    lb: np.ndarray,
    ub: np.ndarray,
    algorithm: str = "LD_LBFGS",
    *,
    ftol_rel: float = 1e-13,
    xtol_rel: float = 1e-11,
    maxeval: int = 500,
    local_algorithm: str = "LD_LBFGS",
    ineq: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    n_ineq: int = 0,
    ineq_tol: float = 1e-10,
    population: int = 0,
    seed: int = 0,
    x_scale: np.ndarray | None = None,
) -> NloptResult:
    """Minimise ``fun`` with nlopt and check the outcome.

    Parameters
    ----------
    fun
        ``fun(x, want_grad) -> (cost, grad)``; ``grad`` may be empty when not wanted.
    x0, lb, ub
        Start and bounds (the start is clipped into the bounds).
    algorithm
        nlopt algorithm name, e.g. ``"LD_LBFGS"`` (see :data:`ALGORITHMS`).
    ftol_rel, xtol_rel, maxeval
        Stopping criteria (relative cost change, relative step, evaluations).
    local_algorithm
        Local optimiser of ``G_MLSL_LDS``.
    ineq, n_ineq, ineq_tol
        Vector inequality constraint ``ineq(x, grad) -> (n_ineq,)`` values, feasible when
        ``<= 0``; fill ``grad`` (n_ineq, n) in place when it is non-empty.
    population, seed
        Population of the stochastic global algorithms and nlopt's random seed.
    x_scale
        Diagonal preconditioner (n,), finite and positive: nlopt searches ``v = x *
        x_scale``.  With ``x_scale = sqrt(d^2 fun / dx^2)`` at the start, the first step
        of a quasi-Newton search (a unit step along ``-grad`` in ``v``) is Newton's step
        instead of one scaled by the gradient's magnitude (which on a 10^5-sample cost
        jumped to a bound and back).  ``fun`` still sees ``x``; the result is in ``x``.

    Returns
    -------
    NloptResult
        The best finite point seen (not only nlopt's last answer).

    Raises
    ------
    FitError
        No finite cost was ever seen, or nlopt rejected the problem.
    """
    code = _algorithm(algorithm)
    x0 = np.clip(np.asarray(x0, dtype=np.float64), lb, ub)
    n = x0.size
    sc = None if x_scale is None else np.asarray(x_scale, dtype=np.float64).reshape(-1)
    if sc is not None and not (sc.shape == (n,) and np.all(np.isfinite(sc) & (sc > 0))):
        sc = None  # an unknown curvature: search x itself
    if ineq is not None:
        sc = None  # (the constraints are functions of x; not worth mapping)
    lb_f = np.asarray(lb, dtype=np.float64)
    ub_f = np.asarray(ub, dtype=np.float64)
    v0 = x0 if sc is None else x0 * sc
    v0_key = v0.tobytes()

    def to_x(v: np.ndarray) -> np.ndarray:
        if sc is None:
            return v
        if v.tobytes() == v0_key:
            return x0.copy()  # exactly the start (v0 / sc need not round back to x0)
        return np.clip(v / sc, lb_f, ub_f)

    best = {"f": np.inf, "x": x0.copy(), "n": 0}
    gradient_based = algorithm.startswith(("LD_", "GD_"))

    secant = _SecantStop(xtol_rel, lb, ub) if (gradient_based and n == 1 and ineq is None) else None

    def obj(v: np.ndarray, grad: np.ndarray) -> float:
        if best.get("secant"):
            # stopped (force_stop below): nlopt may still ask before it looks at the flag;
            # nothing it asks now is taken, so the result does not depend on when it looks
            if grad.size:
                grad[:] = 0.0
            return best["f"]
        best["n"] += 1
        want = grad.size > 0
        x = to_x(v)
        f, g = fun(x, want)
        g_x = None
        if want:
            g_x = np.asarray(g, dtype=np.float64) if np.all(np.isfinite(g)) else np.zeros(n)
            grad[:] = g_x if sc is None else g_x / sc
        if not np.isfinite(f):
            return float("inf")
        if f < best["f"] and (ineq is None or _feasible(x)):
            best["f"], best["x"] = float(f), x.copy()
        # (the secant's Newton step is the same in x and in v: it is tested in x)
        if secant is not None and want and secant.converged(x, g_x, f, best["f"]):
            # nlopt's own stop flag, not an exception through its C++ layer: nlopt 2.11
            # handed a callback's exception back as ForcedStop, a runtime_error or not at
            # once (the search went on for a step), varying from run to run
            best["secant"] = True
            opt.force_stop()
        return float(f)

    def _feasible(x: np.ndarray) -> bool:
        return bool(np.all(ineq(x, np.empty((0, 0))) <= ineq_tol * 10))

    nlopt.srand(seed)
    try:
        opt = nlopt.opt(code, n)
        opt.set_lower_bounds(lb_f if sc is None else lb_f * sc)
        opt.set_upper_bounds(ub_f if sc is None else ub_f * sc)
        opt.set_min_objective(obj)
        opt.set_ftol_rel(ftol_rel)
        opt.set_xtol_rel(xtol_rel)
        opt.set_maxeval(int(maxeval))
        if population:
            opt.set_population(int(population))
        if algorithm == "G_MLSL_LDS":
            loc = nlopt.opt(_algorithm(local_algorithm), n)
            loc.set_ftol_rel(ftol_rel)
            loc.set_xtol_rel(xtol_rel)
            loc.set_maxeval(max(20, int(maxeval) // 10))
            opt.set_local_optimizer(loc)
        if ineq is not None:

            def cons(result: np.ndarray, x: np.ndarray, grad: np.ndarray) -> None:
                result[:] = ineq(x, grad)

            opt.add_inequality_mconstraint(cons, np.full(n_ineq, ineq_tol))
    except GonioError:
        raise
    except Exception as exc:  # nlopt's exceptions have empty messages
        raise FitError(
            f"nlopt rejected the problem for {algorithm} ({type(exc).__name__}: {exc!s} "
            f"- n={n}, bounds finite: {bool(np.all(np.isfinite([lb, ub])))})"
        ) from exc
    status, message = 0, ""
    try:
        opt.optimize(v0)
        status = int(opt.last_optimize_result())
        message = _MESSAGES.get(status, str(status))
    except GonioError:
        raise
    except nlopt.RoundoffLimited:
        status, message = -4, "roundoff limited (best point kept)"
    except nlopt.ForcedStop:
        status, message = -5, "forced stop"
    except nlopt.runtime_error as exc:
        # L-BFGS reports a line search that cannot progress at the minimum as a generic
        # failure (seen on well-conditioned demo data landing on the truth): like
        # round-off, keep the best point; other algorithms still count it as a failure.
        status = -4 if gradient_based else -1
        message = f"{algorithm} failed ({type(exc).__name__})"
    except Exception as exc:  # noqa: BLE001 - nlopt raises bare Exception subclasses
        status = -1
        message = f"{algorithm} failed ({type(exc).__name__}{': ' + str(exc) if str(exc) else ''})"
    if best.get("secant") and status < 0:
        status, message = 4, "xtol reached (secant step)"
    if not np.isfinite(best["f"]):
        raise FitError(
            f"{algorithm}: no finite cost in {best['n']} evaluations from x0={x0.tolist()} "
            f"({message or 'no message'}); the model is NaN or inf on these samples"
        )
    if gradient_based and status == -4 and best["n"] > 1:
        # L-BFGS stops with roundoff when it cannot improve further at machine precision:
        # at a minimum that is convergence, not failure.
        status, message = 1, "converged to round-off"
    return NloptResult(best["x"], best["f"], status, message, best["n"], algorithm)


class _SecantStop:
    """Early exit of 1-D gradient searches (every default candidate with a shape
    parameter): the secant of the last two gradients predicts the Newton step to the
    minimum; once that step is below ``xtol_rel`` the search is done.

    nlopt's L-BFGS tests its tolerances on the steps it takes, and near the minimum of a
    large problem it kept evaluating points that differ in the last bits (8 of 13
    evaluations of a 10^5-sample polish changed the cost by < 1e-15 relative).
    """

    def __init__(self, xtol_rel: float, lb: np.ndarray, ub: np.ndarray) -> None:
        self.tol = float(xtol_rel)
        self.lb = float(np.ravel(lb)[0])
        self.ub = float(np.ravel(ub)[0])
        self.prev: tuple[float, float] | None = None

    def converged(self, x: np.ndarray, grad: np.ndarray, f: float, f_best: float) -> bool:
        xk, gk = float(x[0]), float(grad[0])
        prev, self.prev = self.prev, (xk, gk)
        if prev is None or f > f_best or not np.isfinite(gk):
            return False
        dx = xk - prev[0]
        if dx == 0.0:
            return False
        curv = (gk - prev[1]) / dx
        if not curv > 0.0:
            return False  # not locally convex along the last step: let nlopt decide
        step = gk / curv
        scale = max(abs(xk), 1.0)
        # the secant is local only when the last step was small, and the predicted
        # minimum must lie inside the bounds (else the bound is the answer: nlopt's job)
        return (
            abs(dx) <= 1e-3 * scale
            and abs(step) <= self.tol * scale
            and self.lb <= xk - step <= self.ub
        )


def sobol_design(lb: np.ndarray, ub: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """Scrambled Sobol points (``n`` rounded up to a power of two) in the box [lb, ub].

    The points are those of ``scipy.stats.qmc.Sobol(d, scramble=True, seed=seed)
    .random_base2(m)`` scaled to the box.  For d <= 2 (every default candidate model) they
    are computed here (:func:`_sobol_unit`, held equal to scipy's bit for bit by the
    tests): importing ``scipy.stats`` costs ~0.9 s of a ``gonio fit`` command's ~2 s.
    """
    d = len(lb)
    if d == 0:
        return np.zeros((1, 0))
    m = int(np.ceil(np.log2(max(n, 2))))
    lb = np.asarray(lb, dtype=np.float64)
    ub = np.asarray(ub, dtype=np.float64)
    if d <= 2:
        return lb + _sobol_unit(d, m, seed) * (ub - lb)
    from scipy.stats import qmc

    pts = qmc.Sobol(d, scramble=True, seed=seed).random_base2(m)
    return qmc.scale(pts, lb, ub)


_SOBOL_BITS = 30  # scipy's default resolution


def _sobol_unit(d: int, m: int, seed: int) -> np.ndarray:
    """The first 2**m points of scipy's scrambled Sobol sequence in [0, 1)^d, d <= 2.

    scipy's construction (Joe & Kuo direction numbers; linear matrix scramble + digital
    shift drawn from ``np.random.default_rng(seed)`` in the same order; Gray-code
    order of the points), written with numpy for the first two dimensions, whose direction
    numbers are 1, 1, 1, ... (van der Corput) and those of the polynomial x + 1.
    """
    bits = _SOBOL_BITS
    one = np.uint64(1)
    v = np.zeros((d, bits), dtype=np.uint64)
    v[0, :] = 1
    if d > 1:  # x + 1, m_1 = 1: v_j = v_(j-1) xor 2 v_(j-1)
        v[1, 0] = 1
        for j in range(1, bits):
            v[1, j] = v[1, j - 1] ^ (v[1, j - 1] << one)
    v <<= np.arange(bits - 1, -1, -1, dtype=np.uint64)[None, :]
    rng = np.random.default_rng(seed)
    pow2 = 2 ** np.arange(bits, dtype=np.uint64)
    shift = rng.integers(0, 2, size=(d, bits), dtype=np.uint32).astype(np.uint64) @ pow2
    ltm = np.tril(rng.integers(0, 2, size=(d, bits, bits), dtype=np.uint32)).astype(np.uint64)
    ltm[:, np.arange(bits), np.arange(bits)] = 1
    # row p of each lower-triangular matrix as a bit mask (column k -> bit bits-1-k); the
    # scrambled direction number's bit (bits-1-p) is the parity of (row p & v)
    rows = ltm @ pow2[::-1]  # (d, bits)
    par = np.bitwise_count(rows[:, None, :] & v[:, :, None]) & 1  # (d, j, p)
    sv = (par.astype(np.uint64) * pow2[::-1][None, None, :]).sum(axis=2)  # (d, bits)
    n = 2**m
    # Gray code: point i+1 = point i xor the direction number of the lowest zero bit of i
    i = np.arange(max(n - 1, 0), dtype=np.uint64)
    low0 = np.bitwise_count(((~i) & (i + one)) - one).astype(np.intp)
    steps = sv[:, low0].T  # (n-1, d)
    q = np.bitwise_xor.accumulate(np.vstack([shift[None, :], steps]), axis=0)
    return q[:n].astype(np.float64) / 2.0**bits
