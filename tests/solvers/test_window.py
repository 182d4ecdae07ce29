"""Time-ordered fixed-lag window: same estimate as GTSAM's IncrementalFixedLagSmoother, Bayes tree
in time order (marginalised keys are leaves), less re-elimination per update."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from fgnav.datasets.errors import FlightDataError

import fgnav.solvers.window as window_mod
from fgnav.solvers.fixed_lag import FixedLagOptions, FixedLagRunner, run_fixed_lag
from fgnav.solvers.window import TimeOrderedSmoother, bayes_tree, split_cliques


def _bayes_tree(isam: gtsam.ISAM2) -> tuple[dict, dict, dict, dict]:
    """``fgnav.solvers.window.bayes_tree`` plus each clique's parent."""
    frontals, separators, children = bayes_tree(isam)
    parent = {c: p for p, cs in children.items() for c in cs}
    return frontals, separators, children, parent


def assert_leaves(isam: gtsam.ISAM2, keys) -> None:
    """``ISAM2.marginalizeLeaves(keys)`` replayed on the parsed Bayes tree, key by key in GTSAM's
    order (its release build checks none of this): every clique it removes holds only keys to
    marginalise, in a clique it splits the keys to marginalise lead its frontals, and each key is
    gone after its turn (GTSAM 4.3 strands a leaf clique under a split parent)."""
    keys = sorted(keys)
    leaf = set(keys)
    frontals, separators, children, parent = _bayes_tree(isam)
    clique_of = {k: c for c, fr in frontals.items() for k in fr}
    removed: set[int] = set()

    def remove_subtree(root: str) -> None:
        stack = [root]
        while stack:
            c = stack.pop()
            stray = [k for k in frontals[c] if k not in leaf]
            assert not stray, f"{stray} below marginalised {frontals[root]}"
            removed.update(frontals[c])
            frontals[c] = []
            stack.extend(children.get(c, []))
        if root in parent:
            children[parent[root]].remove(root)

    for key in keys:
        if key in removed:
            continue
        assert key in clique_of, f"{key} not in the Bayes tree"
        c = clique_of[key]
        while c in parent and frontals[parent[c]] and frontals[parent[c]][0] in leaf:
            c = parent[c]
        if all(k in leaf for k in frontals[c]):
            remove_subtree(c)
        else:
            for child in list(children.get(c, [])):
                if any(k in leaf for k in separators[child]):
                    remove_subtree(child)
            mine = [k in leaf for k in frontals[c]]
            n_lead = mine.index(False)
            assert not any(mine[n_lead:]), f"clique {frontals[c]}: not a leading set"
            removed.update(frontals[c][:n_lead])
            frontals[c] = frontals[c][n_lead:]
        assert key in removed, f"{key} left in the tree (its clique hangs under a split clique)"


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


def reference_split(dot_isam: gtsam.ISAM2, gone) -> set[int]:
    """``split_cliques`` the long way, on :func:`bayes_tree`'s dictionaries (integer keys): the
    keys to marginalise of every clique that keeps some of its keys (they must lead it), with
    those of the subtrees whose separator holds them."""
    names = set(gone)
    frontals, separators, children = bayes_tree(dot_isam)
    first: set[int] = set()
    for c, fr in frontals.items():
        mine = [f in names for f in fr]
        if all(mine) or not any(mine):
            continue
        n_lead = mine.index(False)
        assert not any(mine[n_lead:])
        lead = set(fr[:n_lead])
        first |= lead
        for child in children.get(c, []):
            if lead & set(separators[child]):
                stack = [child]
                while stack:
                    x = stack.pop()
                    first.update(f for f in frontals[x] if f in names)
                    stack.extend(children.get(x, []))
    return first


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
    frontals, _, children, _ = _bayes_tree(ours.isam._isam)
    inner_key = next(frontals[c][0] for c in children if chr(frontals[c][0] >> 56) == "x")
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


@pytest.mark.parametrize("seed", range(16))
def test_fuzz_only_leaves_are_marginalised(seed, monkeypatch):
    """Random windows: blocks, lags, fine levels, relinearisation, factorization; late factors,
    loop closures and their removal (a key losing its only factor), stamps raised without a
    factor or lowered, factor-free updates. Before every marginalisation the keys must be leaves
    (``assert_leaves``); the bookkeeping must follow iSAM2's variables; the split cliques read
    from the ``dot()`` text (``split_cliques``) must be those of the parsed tree."""
    splits = []

    def checked_split(dot, gone):
        got = split_cliques(dot, gone)
        assert got == reference_split(sm.isam._isam, gone)
        splits.append(len(got))
        return got

    monkeypatch.setattr(window_mod, "split_cliques", checked_split)
    rng = np.random.default_rng(seed)
    blk, lag = float(rng.choice([0.25, 0.5, 1.0])), float(rng.choice([1.0, 2.0]))
    p = gtsam.ISAM2Params()
    p.enableRelinearization = bool(rng.random() < 0.6)
    p.setRelinearizeThreshold(float(rng.choice([0.001, 0.05])))
    p.relinearizeSkip = int(rng.integers(1, 4))
    p.setFactorization(str(rng.choice(["CHOLESKY", "QR"])))
    p.findUnusedFactorSlots = bool(rng.random() < 0.5)
    sm = TimeOrderedSmoother(lag, p, fine_levels=int(rng.integers(0, 6)))
    sm.isam = _CheckedISAM2(sm.isam)
    X = lambda i: gtsam.symbol("x", i)  # noqa: E731
    Y = lambda i: gtsam.symbol("y", i)  # noqa: E731
    S = lambda i: gtsam.symbol("s", i)  # noqa: E731
    U = lambda i: gtsam.symbol("u", i)  # noqa: E731
    tight, loose, weak = (gtsam.noiseModel.Isotropic.Sigma(6, s) for s in (0.1, 1.0, 10.0))
    step = gtsam.Pose3(gtsam.Rot3(), np.array([0.1, 0.0, 0.0]))
    slow, removable, n_slow, n_u = [], [], 0, 0
    for i in range(90):
        tb = math.ceil(0.1 * i / blk - 1e-9) * blk
        stamps = sm.timestamps()
        cut = max([tb, *stamps.values()]) - lag
        inside = lambda k: k in stamps and stamps[k] >= cut + blk  # noqa: E731, B023
        g, v, st, rm = gtsam.NonlinearFactorGraph(), gtsam.Values(), {}, []
        pose = gtsam.Pose3(gtsam.Rot3(), np.array([0.1 * i, 0.0, 0.0]))
        for key in (X(i), Y(i)):
            v.insert(key, pose)
            st[key] = tb
        if i == 0:
            g.add(gtsam.PriorFactorPose3(X(0), pose, tight))
        else:
            g.add(gtsam.BetweenFactorPose3(X(i - 1), X(i), step, tight))
            g.add(gtsam.BetweenFactorPose3(Y(i - 1), Y(i), step, tight))
        g.add(gtsam.BetweenFactorPose3(X(i), Y(i), gtsam.Pose3(), tight))
        slow = [k for k in slow if k in stamps]
        if i == 0 or rng.random() < 0.1:
            key = S(n_slow)
            n_slow += 1
            v.insert(key, gtsam.Pose3())
            st[key] = tb
            if slow:
                g.add(gtsam.BetweenFactorPose3(slow[-1], key, gtsam.Pose3(), loose))
            else:
                g.add(gtsam.PriorFactorPose3(key, gtsam.Pose3(), loose))
            slow.append(key)
        for key in slow:
            if rng.random() < 0.6:
                g.add(gtsam.BetweenFactorPose3(X(i), key, gtsam.Pose3(), loose))
                st[key] = tb
        extra = []
        old = [k for k in stamps if gtsam.Symbol(k).chr() == ord("x") and inside(k)]
        if old and rng.random() < 0.4:  # late factor or loop closure on an older keyframe
            j = old[int(rng.integers(len(old)))]
            other = slow[-1] if slow and rng.random() < 0.5 else X(i)
            g.add(gtsam.BetweenFactorPose3(j, other, gtsam.Pose3(), loose))
            extra.append(g.size() - 1)
            if other in slow:
                st[other] = tb
        if old and rng.random() < 0.15:  # a key with one factor, removed later (iSAM2 drops it)
            v.insert(U(n_u), pose)
            st[U(n_u)] = tb
            g.add(gtsam.BetweenFactorPose3(X(i), U(n_u), gtsam.Pose3(), loose))
            extra.append(g.size() - 1)
            n_u += 1
        if old and rng.random() < 0.1:  # stamp raised without a factor on the key
            st[old[int(rng.integers(len(old)))]] = tb
        if old and rng.random() < 0.05:  # stamp lowered (still inside the lag), with a factor
            j = old[int(rng.integers(len(old)))]
            g.add(gtsam.PriorFactorPose3(j, gtsam.Pose3(), weak))
            st[j] = stamps[j] - blk
        if removable and rng.random() < 0.3:
            ok = [r for r in removable if all(inside(k) for k in r[1])]
            if ok:
                r = ok[int(rng.integers(len(ok)))]
                removable.remove(r)
                rm = [r[0]]
        if rng.random() < 0.05:
            sm.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), {})
        res = sm.update(g, v, st, rm)
        idx = list(res.getNewFactorsIndices())
        removable += [(idx[e], list(g.at(e).keys())) for e in extra]
        window = set(sm.timestamps())
        assert window == set(sm.isam.getLinearizationPoint().keys())
        assert set(sm._label) <= window
    assert sm.isam.marginalisations >= 4
    assert splits, "no marginalisation read the tree"


def test_split_cliques_of_a_split_clique():
    """A clique whose first keys are marginalised and whose child depends on them: the child's
    subtree goes first; a marginalised key behind a kept one is refused."""
    dot = (
        'digraph G{\n1[label="10, 11, 12"];\n1->2\n2[label="5, 6 : 10, 12"];\n2->3\n'
        '3[label="4 : 5"];\n1->7\n7[label="8 : 11"];\n}'
    )
    assert split_cliques(dot, [10, 5, 6, 4]) == {10, 5, 6, 4}
    assert split_cliques(dot, [10, 11, 8, 5, 6, 4]) == {10, 11, 8, 5, 6, 4}
    assert split_cliques(dot, [5, 6, 4]) == set()  # whole cliques: one call does it
    with pytest.raises(RuntimeError, match="do not lead clique"):
        split_cliques(dot, [11])


def test_held_keys_keep_their_linearisation_point():
    """``hold_linearization``: the keys of marginal factors brought from another smoother are
    never relinearised while in the window (iSAM2's own rule for its marginals); other keys
    are."""
    steps = _chain_problem(40, block_s=1.0)
    p = _params()
    p.setRelinearizeThreshold(1e-6)
    p.relinearizeSkip = 1
    held, free = gtsam.symbol("l", 0), gtsam.symbol("m", 0)
    sm = TimeOrderedSmoother(10.0, p)
    sm.hold_linearization([held])
    first = {}
    for i, (g, v, stamps, _) in enumerate(steps):
        sm.update(g, v, stamps)
        lp = sm.getLinearizationPoint()
        if i == 0:
            first = {k: lp.atPose3(k) for k in (held, free)}
    lp = sm.getLinearizationPoint()
    assert lp.atPose3(held).equals(first[held], 0.0)
    assert not lp.atPose3(free).equals(first[free], 1e-6)


def test_slow_keys_whose_names_collide_are_told_apart():
    """A SLAM session numbered 1000 (as after a relocalisation jump) has alignment keys
    ``S(100000000 + segment)``, which ``gtsam.DefaultKeyFormatter`` prints alike (``s10000000``:
    names are cut to 9 characters). Marginalising an old segment while the next one stays must
    not mistake one for the other (it raised "keys to marginalise do not lead clique" at every
    block, and the online smoother rebuilt each time: 27 rebuilds on MH_01)."""
    assert gtsam.DefaultKeyFormatter(gtsam.symbol("s", 10**8)) == gtsam.DefaultKeyFormatter(
        gtsam.symbol("s", 10**8 + 1)
    )
    rng = np.random.default_rng(5)
    X = lambda i: gtsam.symbol("x", i)  # noqa: E731
    S = lambda j: gtsam.symbol("s", 10**8 + j)  # noqa: E731
    odo = gtsam.noiseModel.Isotropic.Sigma(6, 0.05)
    obs = gtsam.noiseModel.Isotropic.Sigma(6, 0.2)
    walk = gtsam.noiseModel.Isotropic.Sigma(6, 0.01)
    step = gtsam.Pose3.Expmap(np.r_[0.02, -0.01, 0.05, 0.5, 0.1, 0])
    slow = gtsam.Pose3.Expmap(np.r_[0.1, 0.2, -0.3, 2.0, -1.0, 0.5])
    ours = TimeOrderedSmoother(2.0, _params())
    ours.isam = _CheckedISAM2(ours.isam)
    ref = gtsam.IncrementalFixedLagSmoother(2.0, _params())
    x_true = gtsam.Pose3()
    for i in range(80):  # keyframes 0.1 s apart, a slow segment per second, 1 s blocks
        t = 0.1 * i
        blk = float(np.ceil(t - 1e-9))
        seg = int(t + 1e-9)
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if i == 0:
            g.add(gtsam.PriorFactorPose3(X(0), x_true, odo))
        else:
            x_true = x_true.compose(step)
            g.add(gtsam.BetweenFactorPose3(X(i - 1), X(i), step, odo))
        if i == 0 or int(0.1 * (i - 1) + 1e-9) != seg:
            v.insert(S(seg), slow)
            if seg > 0:
                g.add(gtsam.BetweenFactorPose3(S(seg - 1), S(seg), gtsam.Pose3(), walk))
        z = x_true.between(slow).compose(gtsam.Pose3.Expmap(rng.normal(0, 0.02, 6)))
        g.add(gtsam.BetweenFactorPose3(X(i), S(seg), z, obs))
        v.insert(X(i), x_true.compose(gtsam.Pose3.Expmap(rng.normal(0, 0.02, 6))))
        ours.update(g, v, {X(i): blk, S(seg): blk})
        ref.update(g, v, {X(i): blk, S(seg): blk})
    assert ours.isam.marginalisations >= 5
    assert S(0) not in ours and S(7) in ours
    # The same estimate as GTSAM's own fixed-lag smoother (to within its relinearisation).
    a, b = ours.calculateEstimatePose3(X(79)), ref.calculateEstimatePose3(X(79))
    assert np.abs(a.localCoordinates(b)).max() < 0.02
    assert np.abs(a.localCoordinates(x_true)).max() < 0.2


def _counted_chain(n: int, seed: int = 3):
    """``_chain_problem`` with a Python factor (a Pose3 prior as a ``CustomFactor``) on every
    ``x`` key, its callbacks counted in the returned list."""
    calls = [0]
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.5)

    def prior(z):
        def error(this, values, H):
            calls[0] += 1
            x = values.atPose3(this.keys()[0])
            e = z.localCoordinates(x)
            if H is not None:
                H[0] = np.eye(6)  # (GTSAM's Pose3 Logmap Jacobian ~ I near zero error)
            return e

        return error

    steps = []
    for g, v, stamps, newest in _chain_problem(n, block_s=1.0, seed=seed):
        g.add(gtsam.CustomFactor(noise, [newest], prior(v.atPose3(newest))))
        steps.append((g, v, stamps, newest))
    return steps, calls


@pytest.mark.parametrize("relinearize", [False, True])
def test_ballast_keeps_old_changes_off_the_batch_path(relinearize):
    """Ballast: a change at the window's oldest keys re-eliminates the whole time-ordered chain.
    Without ballast iSAM2 then takes its batch path (>= 65 % of the variables affected) and
    relinearises every factor, each Python factor a callback; with ballast it re-eliminates
    incrementally from the cached linearisations. Same estimates (the same factors at the same
    linearisation point), the same marginalisations (leaves only), ballast outside the window's
    bookkeeping, and left behind by ``move_window``."""
    from fgnav.solvers.window import BALLAST, ISAM2_BATCH_THRESHOLD, is_ballast, move_window

    runs = {}
    for ballast in (0.0, 0.6):
        steps, calls = _counted_chain(45)
        p = _params()
        if relinearize:  # old keys relinearise too (the 3 mm position threshold's case)
            p.setRelinearizeThreshold(1e-3)
        sm = TimeOrderedSmoother(2.0, p, ballast=ballast)
        sm.isam = _CheckedISAM2(sm.isam)
        for g, v, stamps, _ in steps:
            sm.update(g, v, stamps)
        # A new factor between the two oldest poses of the window: the whole chain above them.
        oldest = sorted(
            (k for k, t in sm.timestamps().items() if chr(gtsam.Symbol(k).chr()) == "x"),
            key=lambda k: gtsam.Symbol(k).index(),
        )[:2]
        lp = sm.getLinearizationPoint()
        g = gtsam.NonlinearFactorGraph()
        g.add(
            gtsam.BetweenFactorPose3(
                oldest[0],
                oldest[1],
                lp.atPose3(oldest[0]).between(lp.atPose3(oldest[1])),
                gtsam.noiseModel.Isotropic.Sigma(6, 0.05),
            )
        )
        before = calls[0]
        res = sm.update(g, gtsam.Values(), {})
        window = len(sm.timestamps())
        runs[ballast] = dict(
            calls=calls[0] - before,
            reelim=res.getVariablesReeliminated(),
            window=window,
            size=sm.isam.getLinearizationPoint().size(),
            n_ballast=sm.n_ballast,
            est={k: sm.calculateEstimatePose3(k) for k in oldest},
            marg=sm.isam.marginalisations,
            sm=sm,
            n_x=sum(chr(gtsam.Symbol(k).chr()) == "x" for k in sm.timestamps()),
        )
    bare, ball = runs[0.0], runs[0.6]
    assert bare["marg"] == ball["marg"] == 3
    assert bare["n_ballast"] == 0 and bare["size"] == bare["window"]
    # Enough ballast: the whole window below the batch share.
    assert ball["n_ballast"] >= 0.6 * ball["window"]
    assert ball["window"] < ISAM2_BATCH_THRESHOLD * ball["size"]
    assert not any(is_ballast(k) for k in ball["sm"].timestamps())
    # The whole chain re-eliminated either way ...
    assert bare["reelim"] >= bare["window"] - 2 and ball["reelim"] >= 0.7 * ball["window"]
    # ... but without ballast every Python factor of the window was relinearised.
    assert bare["calls"] >= bare["n_x"]
    if relinearize:
        assert ball["calls"] < 0.5 * bare["calls"]
    else:
        assert ball["calls"] == 0
    for k, pose in bare["est"].items():
        assert np.abs(pose.localCoordinates(ball["est"][k])).max() < 1e-6
    # A moved window leaves the ballast behind (the new smoother makes its own).
    new = TimeOrderedSmoother(2.0, _params(), ballast=0.6)
    move_window(ball["sm"], new)
    lp = new.getLinearizationPoint()
    assert set(new.timestamps()) == set(ball["sm"].timestamps())
    assert new.n_ballast >= 0.6 * len(new.timestamps())
    assert lp.exists(BALLAST(0)) and not lp.exists(BALLAST(new.n_ballast))
    k = next(iter(ball["est"]))
    assert np.abs(new.calculateEstimatePose3(k).localCoordinates(ball["est"][k])).max() < 1e-6
    with pytest.raises(ValueError, match="ballast"):
        TimeOrderedSmoother(1.0, _params(), ballast=-1.0)
