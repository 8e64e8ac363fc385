"""A fixed-lag keyframe window over GTSAM factors with real marginalization.

Each keyframe i owns three variables (``gtsam.symbol_shorthand``):
    X(i): Pose3 T_map_body, V(i): velocity of the body in the map frame (m/s),
    B(i): imuBias.ConstantBias (imu frame).
In LiDAR-only tracking V(i) is the body twist (6,) (rad/s, m/s; ``blockloc.tracking.motion``) and
there is no B(i): marginalization only touches the keys that exist.
The window holds at most ``max_size`` keyframes. Dropping the oldest ones is a Schur complement,
done here by hand: every factor touching the dropped variables is linearized at the current
estimate, the dropped variables are eliminated (``eliminatePartialSequential``), and the
remaining Gaussian factor on the separator becomes a ``LinearContainerFactor`` (linearized at the
marginalization point). So :meth:`marginalize_to` can shrink the window to any size (5 at a
map switch) and the window grows back as keyframes are added.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger(__name__)


def keys_of(index: int) -> tuple[int, int, int]:
    """(X, V, B) keys of keyframe ``index``."""
    from gtsam.symbol_shorthand import B, V, X

    return X(index), V(index), B(index)


@dataclass
class _Entry:
    factor: object
    keys: frozenset


@dataclass
class WindowStats:
    size: int = 0
    marginalized: int = 0  # keyframes marginalized by the last call
    optimize_ms: float = 0.0
    iterations: int = 0
    error: float = 0.0


class SlidingWindow:
    """Keyframes in time order, their factors, the current estimate.

    max_size: N_a, the window length in keyframes (>= 1).
    max_iterations: Levenberg-Marquardt iterations per :meth:`optimize`.
    one_step_m, one_step_rad: :meth:`optimize` stops after its first iteration when that moved
        every pose by less than these (metres, radians; both 0: never), see there.
    """

    def __init__(self, max_size: int = 20, max_iterations: int = 6, one_step_m: float = 0.01,
                 one_step_rad: float = 0.0035) -> None:
        import gtsam

        if max_size < 1:
            raise ValueError(f"window size {max_size}: expected >= 1")
        self.max_size = max_size
        self.one_step_m = float(one_step_m)
        self.one_step_rad = float(one_step_rad)
        self.keyframes: list[int] = []
        self.stamps: dict[int, float] = {}
        self._factors: list[_Entry] = []
        self.values = gtsam.Values()
        self._lm = gtsam.LevenbergMarquardtParams()
        self._lm.setMaxIterations(max_iterations)
        self._lm.setRelativeErrorTol(1e-5)
        self._lm.setAbsoluteErrorTol(1e-6)
        self.stats = WindowStats()

    # ----------------------------------------------------------------- building
    def __len__(self) -> int:
        return len(self.keyframes)

    @property
    def latest(self) -> int | None:
        return self.keyframes[-1] if self.keyframes else None

    def clear(self) -> None:
        import gtsam

        self.keyframes.clear()
        self.stamps.clear()
        self._factors.clear()
        self.values = gtsam.Values()

    def add_keyframe(self, index: int, stamp: float, initial) -> None:
        """Add keyframe ``index`` (increasing) with ``initial`` gtsam.Values for its X, V, B."""
        if self.keyframes and index <= self.keyframes[-1]:
            raise ValueError(f"keyframe {index} is not after {self.keyframes[-1]}")
        self.keyframes.append(index)
        self.stamps[index] = stamp
        self.values.insert(initial)

    def add_factor(self, factor) -> None:
        """Add a nonlinear factor whose keys are all in the window."""
        self._factors.append(_Entry(factor, frozenset(factor.keys())))

    def graph(self):
        """The window's NonlinearFactorGraph (a fresh container, the same factor objects)."""
        import gtsam

        g = gtsam.NonlinearFactorGraph()
        for e in self._factors:
            g.add(e.factor)
        return g

    @property
    def num_factors(self) -> int:
        return len(self._factors)

    # ----------------------------------------------------------------- solving
    def optimize(self) -> None:
        """Levenberg-Marquardt over the whole window from the current estimate.

        One iteration is enough when it moved no pose of the window by ``one_step_m`` or
        ``one_step_rad`` or more: the next one would correct by about the square of that step
        times the problem's nonlinearity. Why: with a keyframe per scan the window starts each
        frame next to its optimum, and LM's relative-error test always asked for a second
        iteration that changed nothing (measured on the small world, seed 2, 100 frames: first
        steps of the newest pose 5 mm median, 28 mm at most; the second iteration moved the
        window's poses by 0.6 um median, 0.4 mm at most), half the smoother's time. Otherwise
        (a restart, a large correction) the iterations go on up to ``max_iterations``.
        """
        import time

        import gtsam

        t0 = time.perf_counter()
        graph = self.graph()
        opt = gtsam.LevenbergMarquardtOptimizer(graph, self.values, self._lm)
        if self.keyframes and (self.one_step_m > 0 or self.one_step_rad > 0):
            before = gtsam.utilities.extractPose3(self.values)  # (K, 12): rotation rows, translation
            opt.iterate()
            after = gtsam.utilities.extractPose3(opt.values())
            d = after - before
            # |R1 - R0|_F = 2 sqrt(2) sin(angle / 2): about sqrt(2) x the angle between them
            moved_m = float(np.sqrt((d[:, 9:] ** 2).sum(axis=1)).max()) if len(d) else 0.0
            turned_rad = float(np.sqrt((d[:, :9] ** 2).sum(axis=1)).max()) / np.sqrt(2.0) if len(d) else 0.0
            if moved_m >= self.one_step_m or turned_rad >= self.one_step_rad:
                opt.optimize()  # goes on from the first iteration's estimate
        else:
            opt.optimize()
        self.values = gtsam.Values(opt.values())
        self.stats.optimize_ms = (time.perf_counter() - t0) * 1e3
        self.stats.iterations = opt.iterations()
        self.stats.error = opt.error()

    def covariance(self, key) -> np.ndarray:
        """Marginal covariance of one variable at the current estimate (tangent space)."""
        return self.frozen().covariance(key)

    def joint_covariance(self, keys) -> np.ndarray:
        """Joint marginal covariance of several variables, blocks in the order of ``keys``."""
        return self.frozen().joint_covariance(keys)

    def frozen(self) -> "FrozenWindow":
        """The window's factors and estimate as they are now, for marginals asked for later (the
        window itself moves on with the next frame). Cheap: a list of the same factor objects and
        a copy of the values (microseconds); the marginals are computed only when asked."""
        import gtsam

        return FrozenWindow([e.factor for e in self._factors], gtsam.Values(self.values))

    def marginalize_to(self, n_keep: int) -> int:
        """Keep the newest ``n_keep`` keyframes, turn the rest into a prior; returns how many went."""
        import gtsam

        n_keep = max(1, n_keep)
        n_drop = len(self.keyframes) - n_keep
        self.stats.marginalized = 0
        if n_drop <= 0:
            return 0
        dropped = self.keyframes[:n_drop]
        drop_keys = set()
        for i in dropped:
            drop_keys.update(keys_of(i))
        involved = [e for e in self._factors if e.keys & drop_keys]
        rest = [e for e in self._factors if not e.keys & drop_keys]

        nl = gtsam.NonlinearFactorGraph()
        for e in involved:
            nl.add(e.factor)
        linear = nl.linearize(self.values)
        present = [k for k in drop_keys if self.values.exists(k)]
        _, remaining = linear.eliminatePartialSequential(gtsam.KeyVector(present))

        # each LinearContainerFactor keeps the values of its own keys only: the whole estimate will do
        prior = gtsam.LinearContainerFactor.ConvertLinearGraph(remaining, self.values)
        self._factors = rest
        for i in range(prior.size()):
            f = prior.at(i)
            if f is not None and len(f.keys()) > 0:
                self.add_factor(f)
        for k in present:
            self.values.erase(k)
        for i in dropped:
            self.stamps.pop(i, None)
        self.keyframes = self.keyframes[n_drop:]
        self.stats.marginalized = n_drop
        return n_drop

    def enforce_size(self, switched: bool, size_on_switch: int) -> int:
        """Marginalize down to N_r on a switch, else down to N_a; returns keyframes dropped."""
        return self.marginalize_to(size_on_switch if switched else self.max_size)


class FrozenWindow:
    """A window's factor graph and estimate at one moment (:meth:`SlidingWindow.frozen`): marginal
    covariances of its variables, tangent space, computed on the first request."""

    def __init__(self, factors: list, values) -> None:
        self._factors = factors
        self._values = values
        self._marginals = None

    def _get(self):
        import gtsam

        if self._marginals is None:
            g = gtsam.NonlinearFactorGraph()
            for f in self._factors:
                g.add(f)
            self._marginals = gtsam.Marginals(g, self._values)
        return self._marginals

    def covariance(self, key) -> np.ndarray:
        """Marginal covariance of one variable."""
        return np.asarray(self._get().marginalCovariance(key))

    def joint_covariance(self, keys) -> np.ndarray:
        """Joint marginal covariance of several variables, blocks in the order of ``keys``."""
        import gtsam

        joint = self._get().jointMarginalCovariance(gtsam.KeyVector(list(keys)))
        return np.block([[np.asarray(joint.at(a, b)) for b in keys] for a in keys])

