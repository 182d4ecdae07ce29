"""Time-ordered fixed-lag window: same estimate as GTSAM's IncrementalFixedLagSmoother, Bayes tree
in time order (marginalised keys are leaves), less re-elimination per update."""

from __future__ import annotations

import re

import gtsam
import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError

from fgnav.solvers.fixed_lag import FixedLagOptions, FixedLagRunner, run_fixed_lag
from fgnav.solvers.window import TimeOrderedSmoother

_CLIQUE = re.compile(r'^(\d+)\[label="([^"]*)"\];$')
_EDGE = re.compile(r"^(\d+)->(\d+)$")


def _bayes_tree(isam: gtsam.ISAM2) -> tuple[dict[str, list[str]], dict[str, list[str]]]:
    """Frontal key names of each clique (in elimination order) and each clique's children, from
    ``ISAM2.dot()``."""
    frontals: dict[str, list[str]] = {}
    children: dict[str, list[str]] = {}
    for line in isam.dot().splitlines():
        line = line.strip()
        if m := _CLIQUE.match(line):
            frontals[m.group(1)] = [k.strip() for k in m.group(2).split(":")[0].split(",")]
        elif m := _EDGE.match(line):
            children.setdefault(m.group(1), []).append(m.group(2))
    return frontals, children


def assert_leaves(isam: gtsam.ISAM2, keys) -> None:
    """The keys to marginalise lead their cliques' frontals and every clique below holds only
    keys to marginalise (what ``ISAM2.marginalizeLeaves`` needs; release builds do not check)."""
    names = {gtsam.DefaultKeyFormatter(k) for k in keys}
    frontals, children = _bayes_tree(isam)
    for cid, fr in frontals.items():
        mine = [f in names for f in fr]
        if not any(mine):
            continue
        n_lead = mine.index(False) if False in mine else len(mine)
        assert all(mine[:n_lead]) and not any(mine[n_lead:]), f"clique {fr}: not a leading set"
        stack = list(children.get(cid, []))
        while stack:
            c = stack.pop()
            assert all(f in names for f in frontals[c]), f"{frontals[c]} below marginalised {fr}"
            stack.extend(children.get(c, []))


class _CheckedISAM2:
    """Delegates to an ISAM2 and checks the leaf property before every marginalisation."""

    def __init__(self, isam):
        self._isam = isam
        self.marginalisations = 0

    def marginalizeLeaves(self, keys):  # noqa: N802
        assert_leaves(self._isam, _to_list(keys))
        self.marginalisations += 1
        return self._isam.marginalizeLeaves(keys)

    def __getattr__(self, name):
        return getattr(self._isam, name)


def _to_list(keys: gtsam.KeyList) -> list[int]:
    """The keys of a KeyList (rotated through once: the list is unchanged)."""
    out = []
    for _ in range(keys.size()):
        k = keys.front()
        keys.pop_front()
        keys.push_back(k)
        out.append(k)
    return out


def _params() -> gtsam.ISAM2Params:
    p = gtsam.ISAM2Params()
    p.setRelinearizeThreshold(0.05)
    p.relinearizeSkip = 3
    p.setFactorization("CHOLESKY")
    p.findUnusedFactorSlots = True
    return p


def _chain_problem(n: int, block_s: float, seed: int = 3):
    """Keyframes 0.1 s apart shaped like the real graph's: two states per keyframe (poses ``x`` and
    ``y``, tied to each other like the pose and velocity of an IMU factor) with odometry between
    consecutive keyframes, and two slow variables (Pose3 ``l`` and ``m``, like the SLAM alignment
    and the drag) measured from every keyframe, so they sit in every separator. Per step: graph,
    values, stamps (rounded up to ``block_s`` blocks; the slow keys re-stamped at every step) and
    the newest ``x`` key."""
    rng = np.random.default_rng(seed)
    X = lambda i: gtsam.symbol("x", i)  # noqa: E731
    Y = lambda i: gtsam.symbol("y", i)  # noqa: E731
    L, M = gtsam.symbol("l", 0), gtsam.symbol("m", 0)
    odo = gtsam.noiseModel.Isotropic.Sigma(6, 0.05)
    obs = gtsam.noiseModel.Isotropic.Sigma(6, 0.2)
    step = gtsam.Pose3.Expmap(np.r_[0.02, -0.01, 0.05, 0.5, 0.1, 0])
    offset = gtsam.Pose3.Expmap(np.r_[0.0, 0.1, 0.0, 0.2, 0.0, -0.1])
    x_true = [gtsam.Pose3()]
    for _ in range(1, n):
        x_true.append(x_true[-1].compose(step))
    y_true = [x.compose(offset) for x in x_true]
    slow_true = {
        L: gtsam.Pose3.Expmap(np.r_[0.1, 0.2, -0.3, 2.0, -1.0, 0.5]),
        M: gtsam.Pose3.Expmap(np.r_[-0.2, 0.1, 0.3, -1.0, 0.5, 2.0]),
    }

    def noisy(pose, sigma):
        return pose.compose(gtsam.Pose3.Expmap(rng.normal(0, sigma, 6)))

    steps = []
    for i in range(n):
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        blk = np.ceil(0.1 * i / block_s - 1e-9) * block_s
        stamps = {X(i): blk, Y(i): blk, L: blk, M: blk}
        if i == 0:
            g.add(gtsam.PriorFactorPose3(X(0), x_true[0], odo))
            for key, val in slow_true.items():
                v.insert(key, noisy(val, 0.05))
        else:
            for S, tr in ((X, x_true), (Y, y_true)):
                z = noisy(tr[i - 1].between(tr[i]), 0.01)
                g.add(gtsam.BetweenFactorPose3(S(i - 1), S(i), z, odo))
        g.add(gtsam.BetweenFactorPose3(X(i), Y(i), noisy(offset, 0.01), odo))
        for S, tr, key in ((X, x_true, L), (Y, y_true, M)):
            z = noisy(tr[i].between(slow_true[key]), 0.05)
            g.add(gtsam.BetweenFactorPose3(S(i), key, z, obs))
        v.insert(X(i), noisy(x_true[i], 0.05))
        v.insert(Y(i), noisy(y_true[i], 0.05))
        steps.append((g, v, stamps, X(i)))
    return steps


def test_time_ordered_matches_incremental_fixed_lag_smoother():
    steps = _chain_problem(120, block_s=1.0)
    ours = TimeOrderedSmoother(2.0, _params(), fine_levels=4)
    ours.isam = _CheckedISAM2(ours.isam)
    ref = gtsam.IncrementalFixedLagSmoother(2.0, _params())
    reelim, relin, err = {"ours": [], "ref": []}, {"ours": [], "ref": []}, []
    for g, v, stamps, newest in steps:
        ours.update(g, v, stamps)
        ref.update(g, v, stamps)
        for name, res in (("ours", ours.getISAM2Result()), ("ref", ref.getISAM2Result())):
            reelim[name].append(res.getVariablesReeliminated())
            relin[name].append(res.getVariablesRelinearized())
        a, b = ours.calculateEstimatePose3(newest), ref.calculateEstimatePose3(newest)
        err.append(np.abs(a.localCoordinates(b)).max())
    # Same factors, same marginalisation times: the same estimate (orderings differ: rounding).
    assert max(err) < 1e-6
    assert ours.isam.marginalisations == 10  # one 1 s block per second once the lag is full
    assert set(ours.timestamps()) == set(ref.timestamps())
    # Window bounded: at most 2 s lag + one 1 s block of 0.1 s keyframes (2 keys each) + 2 slow.
    assert len(ours.timestamps()) <= 2 * 31 + 2
    assert ours.reorders == 0 and ours.unordered_updates == 0
    # Without relinearisation an update re-eliminates the root clique and the one below (the
    # newest keyframes and the slow keys): at most 13 variables in this run, where GTSAM's
    # smoother re-eliminated up to 66 when it marginalised.
    steady = {name: np.array(reelim[name][30:])[np.array(relin[name][30:]) == 0] for name in reelim}
    assert steady["ours"].max() <= 14
    assert steady["ref"].max() >= 3 * steady["ours"].max()
    assert np.mean(reelim["ours"][30:]) < 0.85 * np.mean(reelim["ref"][30:])
    # The leaf check itself: the leading key of a clique with children is not a leaf.
    frontals, children = _bayes_tree(ours.isam._isam)
    inner = next(frontals[c][0] for c in children if frontals[c][0].startswith("x"))
    inner_key = next(k for k in ours.timestamps() if gtsam.DefaultKeyFormatter(k) == inner)
    with pytest.raises(AssertionError, match="below marginalised"):
        assert_leaves(ours.isam._isam, [inner_key])
    assert_leaves(ours.isam._isam, [k for k, t in ours.timestamps().items() if t == 10.0])


def test_unordered_update_is_reordered_before_marginalisation():
    """An update whose new factors have fewer keys than there are stamp blocks cannot carry the
    block groups (CCOLAMD labels must stay below the number of re-eliminated variables): the
    window is then re-eliminated in order before the next marginalisation."""
    steps = _chain_problem(60, block_s=1.0)
    ours = TimeOrderedSmoother(2.0, _params(), fine_levels=2)
    ours.isam = _CheckedISAM2(ours.isam)
    for i, (g, v, stamps, _) in enumerate(steps):
        ours.update(g, v, stamps)
        if i == 35:  # a factor-free update (nothing new): no groups possible
            ours.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), {})
    assert ours.unordered_updates == 1
    assert ours.reorders == 1
    assert ours.isam.marginalisations == 4


def test_many_small_blocks_reorder_at_every_marginalisation():
    """0.3 s blocks under a 2 s lag: more blocks than keys per update, so no update can carry the
    groups; every marginalisation then re-orders the window first, and still only marginalises
    leaves, with the estimate of the reference smoother to within its relinearisation."""
    steps = _chain_problem(60, block_s=0.3)
    ours = TimeOrderedSmoother(2.0, _params())
    ours.isam = _CheckedISAM2(ours.isam)
    ref = gtsam.IncrementalFixedLagSmoother(2.0, _params())
    for g, v, stamps, _ in steps:
        ours.update(g, v, stamps)
        ref.update(g, v, stamps)
    newest = steps[-1][3]
    assert ours.unordered_updates > 30
    assert ours.reorders == ours.isam.marginalisations >= 12
    a, b = ours.calculateEstimatePose3(newest), ref.calculateEstimatePose3(newest)
    assert np.abs(a.localCoordinates(b)).max() < 0.05


def test_time_ordered_rejects_bad_arguments():
    with pytest.raises(ValueError, match="lag_s"):
        TimeOrderedSmoother(0.0, _params())
    with pytest.raises(ValueError, match="fine_levels"):
        TimeOrderedSmoother(1.0, _params(), fine_levels=-1)
    with pytest.raises(RuntimeError, match="no update"):
        TimeOrderedSmoother(1.0, _params()).getISAM2Result()


def test_runner_time_ordered_equals_gtsam_smoother(two_turns_12s):
    """The fixed-lag runner with either window gives the same causal trajectory; the time-ordered
    one marginalises only leaves (checked on its Bayes tree) and re-eliminates less."""
    r = FixedLagRunner(two_turns_12s, FixedLagOptions(lag_s=2.0))
    checked = []

    def new_smoother(factorization, make=r._new_smoother):
        s = make(factorization)
        s.isam = _CheckedISAM2(s.isam)
        checked.append(s.isam)
        return s

    r._new_smoother = new_smoother
    r.smoother = new_smoother(r.factorization)
    ordered = r.run()
    ref = run_fixed_lag(two_turns_12s, FixedLagOptions(lag_s=2.0, smoother="gtsam"))
    assert ordered.info["smoother"] == "time-ordered" and ref.info["smoother"] == "gtsam"
    assert ordered.info["window_reorders"] == 0 and ordered.info["window_unordered_updates"] == 0
    assert sum(c.marginalisations for c in checked) >= 8
    d = np.linalg.norm(ordered.trajectory.world_t_body - ref.trajectory.world_t_body, axis=1)
    assert d.max() < 1e-4, d.max()
    assert ordered.slam_scale.keys() == ref.slam_scale.keys()
    for sess, scale in ordered.slam_scale.items():
        assert abs(scale - ref.slam_scale[sess]) < 1e-5


def test_runner_rejects_unknown_smoother(two_turns_12s):
    with pytest.raises(FlightDataError, match="smoother"):
        FixedLagRunner(two_turns_12s, FixedLagOptions(smoother="batch"))
    with pytest.raises(FlightDataError, match="fine_levels"):
        FixedLagRunner(two_turns_12s, FixedLagOptions(fine_levels=-2))


def test_callbacks_get_the_linearisation_point_without_a_copy():
    """CustomFactor callbacks inside iSAM2 receive the smoother's registered view of its
    linearisation point (pybind11 passes an existing wrapper instead of copying the window)."""
    sm = TimeOrderedSmoother(2.0, _params())
    seen = []

    def error(this, values, H):
        seen.append(values)
        if H is not None:
            H[0] = np.eye(6)
        return np.zeros(6)

    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    for g, v, stamps, newest in _chain_problem(15, block_s=1.0):
        g.add(gtsam.CustomFactor(noise, [newest], error))
        sm.update(g, v, stamps)
    assert len(seen) >= 15
    assert all(s is sm._theta_view for s in seen)
    # The view is live: it holds the window's current linearisation point.
    assert sm._theta_view.size() == sm.isam.getLinearizationPoint().size() == len(sm.timestamps())


def test_runner_uses_gtsam_window_for_small_marginalisation_blocks(two_turns_12s, caplog):
    """Blocks shorter than a quarter of the lag need more ordering groups than an update has keys:
    the runner then uses GTSAM's smoother, says so, and reports it."""
    opts = FixedLagOptions(lag_s=2.0, marginalize_every_s=0.0)
    with caplog.at_level("WARNING", logger="fgnav.solvers.fixed_lag"):
        r = FixedLagRunner(two_turns_12s, opts)
    assert r.smoother_kind == "gtsam"
    assert isinstance(r.smoother, gtsam.IncrementalFixedLagSmoother)
    assert "marginalize_every_s=0" in caplog.text
    r_half = FixedLagRunner(two_turns_12s, FixedLagOptions(lag_s=2.0, marginalize_every_s=0.5))
    assert r_half.smoother_kind == "time-ordered"
    assert isinstance(r_half.smoother, TimeOrderedSmoother)
