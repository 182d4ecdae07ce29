"""Fixed-lag iSAM2 smoother that keeps its Bayes tree in time order.

``gtsam.IncrementalFixedLagSmoother`` orders the re-eliminated part of the Bayes tree with at most
two groups (variables to marginalise first, all others after) and otherwise leaves the order to
CCOLAMD, which on a keyframe chain tied to a few slow variables (SLAM alignment, drag, ground
height: in every clique's separator) puts the root in the middle of the window and the newest
keyframe at the bottom of a chain of cliques. Every later update then re-eliminates that whole
chain (about 30 variables per 20 Hz keyframe on the 2 s window), and every marginalisation marks
the cliques below the marginalised keys (about 100 variables once per block).

``TimeOrderedSmoother`` wraps ``gtsam.ISAM2`` directly and gives every update CCOLAMD constraint
groups that follow time:

* a key's *marginalisation stamp* (the timestamp given with it, rounded by the caller into blocks)
  orders it first: keys of an older block are always eliminated before keys of a newer block;
* within the newest block, the keys given in the last ``fine_levels`` updates get one group per
  update (newest last), so the newest keyframe and the slow variables it measures sit at the root
  and a new keyframe re-eliminates only the few cliques above the oldest key its factors touch.

Elimination order consistent with the stamps makes the keys to marginalise (the oldest block)
leaves of the Bayes tree, so ``ISAM2.marginalizeLeaves`` runs without re-eliminating anything.
The invariant holds by induction: each update re-orders the removed top of the tree with the
groups, the orphaned subtrees keep their older, consistent order, and a key whose stamp grows
(a slow variable still measured) is one of the update's keys, so its path to the root is
re-ordered (a key re-stamped without a new factor on it is re-eliminated explicitly). CCOLAMD
needs every group label < the number of re-eliminated variables, which is at least the number of
keys of the update's new factors; when the block groups alone do not fit (or a stamp decreased),
the update runs unconstrained, the tree is marked out of order, and before the next
marginalisation the whole window is re-eliminated with the block groups (``reorders``) so the
marginalised keys are leaves again. Keys iSAM2 drops (all their factors removed) leave the
bookkeeping; a new value without a stamp is refused. GTSAM's release builds do not check that
marginalised keys are leaves (a non-leaf silently corrupts the tree), hence these rules; a fuzz
test of random stamps, removals and late factors checks the leaves before every marginalisation.
Marginalisation itself runs in two ``marginalizeLeaves`` calls when a clique keeps some of its
keys (split cliques and what depends on them first): GTSAM 4.3 mishandles one call there (see
``_split_cliques_first``). The tree is read from ``ISAM2.dot()`` for that, once per block.

Ballast (``ballast``): ``ISAM2::recalculate`` re-eliminates in *batch* when an update affects at
least 65 % of its variables (``batchThreshold``, a constant of GTSAM 4.3): it then relinearises
every factor of the window at its linearisation point (each ``CustomFactor`` a Python callback)
instead of taking the cached linearisations. In a time-ordered tree any change at the oldest keys (a
relinearised old keyframe pose) affects the whole chain up to the root, so it always took the batch
path. Measured on the 60 s figure8 benchmark (load 4, thread CPU time): re-eliminating the whole
window from its oldest key with nothing relinearised, 16.6 ms (154 variables, every factor
relinearised) against 2.5 ms (134 variables, cached linearisations) with ballast. Ballast variables
(``BALLAST(i)``: a 1-D vector with a unit prior each, their own root cliques, never touched again)
keep the window below that share. The estimate is the same (the same factors at the same
linearisation point, up to the elimination order's rounding); only the relinearisation of factors
whose variables did not move is spared. It costs a few more cliques in the tree (read once per
block, see below) and is worth it only where old keys relinearise
(``FixedLagOptions.relinearize_threshold_position``).

Callbacks: GTSAM's Python wrapper hands every ``CustomFactor`` callback the Values it linearises
at; for iSAM2's own linearisation point that was a copy of the whole window per callback (about
45 us at 200 values, 20 % of an update on the benchmark) unless a Python object already wraps
that Values: the smoother keeps such a view (``getLinearizationPoint()``) alive, and pybind11 then
passes it instead of a copy. The callbacks read the live linearisation point, as the C++ code does.

Interface: the subset of ``IncrementalFixedLagSmoother`` the fixed-lag runner uses
(``update(graph, values, stamps, remove)``, ``calculateEstimate*``, ``getFactors``,
``getLinearizationPoint``, ``timestamps``, ``getISAM2Result``).
"""

from __future__ import annotations

import re
from collections import deque
from collections.abc import Iterable
from typing import Any

import gtsam
import numpy as np

#: The lines of an ``ISAM2.dot()`` text, found in one pass over the whole text: clique id and
#: label (frontal keys, then `` : `` and the separator keys, absent at a root; keys
#: ``", "``-separated), and parent -> child edges.
_CLIQUE_ALL = re.compile(r'^(\d+)\[label="([^"]*)"\];$', re.M)
_EDGE_ALL = re.compile(r"^(\d+)->(\d+)$", re.M)


#: ``iSAM2``'s share of affected variables from which it re-eliminates in batch (GTSAM 4.3
#: ``ISAM2.cpp``: ``batchThreshold``, not a parameter).
ISAM2_BATCH_THRESHOLD = 0.65


def BALLAST(i: int) -> int:  # noqa: N802 (named as the keys of fgnav.keys)
    """Key of ``TimeOrderedSmoother``'s i-th ballast variable (symbol ``z``)."""
    return gtsam.symbol("z", i)


def is_ballast(key: int) -> bool:
    """Is ``key`` a ballast variable (``BALLAST``)?"""
    return gtsam.Symbol(key).chr() == ord("z")


def bayes_tree(
    isam: gtsam.ISAM2,
) -> tuple[dict[str, list[int]], dict[str, list[int]], dict[str, list[str]]]:
    """The Bayes tree of ``isam`` from ``ISAM2.dot()`` (the Python wrapper has no clique
    access): per clique id, its frontal keys (elimination order), its separator keys and its
    children's ids. Keys are read as integers (``dot(str)``): ``gtsam.DefaultKeyFormatter``
    cuts a symbol's name to 9 characters, so ``S(100000000)`` and ``S(100000001)`` (the first
    segments of a SLAM session numbered 1000, as after a relocalisation jump) both print as
    ``s10000000`` and could not be told apart."""
    frontals: dict[str, list[int]] = {}
    separators: dict[str, list[int]] = {}
    children: dict[str, list[str]] = {}
    dot = isam.dot(str)
    for c, label in _CLIQUE_ALL.findall(dot):
        fr_text, _, sep_text = label.partition(" : ")
        frontals[c] = [int(k) for k in fr_text.split(", ")]
        separators[c] = [int(k) for k in sep_text.split(", ")] if sep_text else []
    for parent, child in _EDGE_ALL.findall(dot):
        children.setdefault(parent, []).append(child)
    return frontals, separators, children


def split_cliques(dot: str, gone: Iterable[int]) -> set[int]:
    """The keys of ``gone`` in the cliques that keep some of their keys, with those of the
    subtrees that depend on them (``TimeOrderedSmoother._split_cliques_first``), from the text of
    ``ISAM2.dot(str)``. The same result as walking :func:`bayes_tree`'s dictionaries, in one
    regular-expression pass with the keys compared as text and turned into integers only where
    a clique is split: parsing every clique's keys into integers took about as long as GTSAM's
    ``dot()`` itself (0.5-0.6 ms per marginalisation on the 180 s benchmark window).

    Raises:
        RuntimeError: keys to marginalise that do not lead their clique.
    """
    names = {str(k) for k in gone}
    frontals: dict[str, list[str]] = {}
    separators: dict[str, str] = {}
    split: list[tuple[str, set[str]]] = []
    for c, label in _CLIQUE_ALL.findall(dot):
        fr_text, _, sep_text = label.partition(" : ")
        fr = fr_text.split(", ")
        frontals[c], separators[c] = fr, sep_text
        if names.isdisjoint(fr) or names.issuperset(fr):
            continue
        mine = [f in names for f in fr]
        n_lead = mine.index(False)
        if any(mine[n_lead:]):
            raise RuntimeError(
                "TimeOrderedSmoother: keys to marginalise do not lead clique "
                f"{[gtsam.DefaultKeyFormatter(int(f)) for f in fr]}"
            )
        split.append((c, set(fr[:n_lead])))
    if not split:
        return set()
    children: dict[str, list[str]] = {}
    for parent, child in _EDGE_ALL.findall(dot):
        children.setdefault(parent, []).append(child)
    first: set[str] = set()
    for c, lead in split:
        first |= lead
        for child in children.get(c, []):
            if lead & set(separators[child].split(", ")):
                stack = [child]
                while stack:
                    x = stack.pop()
                    first.update(f for f in frontals[x] if f in names)
                    stack.extend(children.get(x, []))
    return {int(k) for k in first}


def _key_list(keys: Iterable[int]) -> gtsam.KeyList:
    out = gtsam.KeyList()
    for k in keys:
        out.push_back(k)
    return out


class TimeOrderedSmoother:
    """iSAM2 over a sliding window with time-ordered elimination (see module docstring).

    Args:
        lag_s: keys whose stamp is older than the newest stamp minus ``lag_s`` are marginalised.
        params: ``gtsam.ISAM2Params``.
        fine_levels: number of most recent updates whose keys get their own constraint group
            within the newest stamp block (0: blocks only).
        ballast: keep at least this many ballast variables per window variable (plus 2), so
            that re-eliminating the whole window stays below iSAM2's batch threshold (see the
            module docstring; 0: none; above ``1 / ISAM2_BATCH_THRESHOLD - 1`` = 0.54 for that).
            ``params`` needs a relinearisation threshold entry for symbol ``z`` (1-D) when its
            thresholds are per symbol.
    """

    def __init__(
        self, lag_s: float, params: gtsam.ISAM2Params, fine_levels: int = 4, ballast: float = 0.0
    ):
        if not lag_s > 0:
            raise ValueError(f"lag_s must be > 0, got {lag_s}")
        if fine_levels < 0:
            raise ValueError(f"fine_levels must be >= 0, got {fine_levels}")
        if not ballast >= 0:
            raise ValueError(f"ballast must be >= 0, got {ballast}")
        self.lag_s = float(lag_s)
        self.fine_levels = int(fine_levels)
        self.isam = gtsam.ISAM2(params)
        # A Python view of iSAM2's linearisation point: while it is alive, pybind11 hands this
        # registered object to the CustomFactor callbacks instead of copying the whole window's
        # Values for every callback (measured: ~45 us per callback at 200 values).
        self._theta_view = self.isam.getLinearizationPoint()
        self._stamp: dict[int, float] = {}
        self._blocks: dict[float, set[int]] = {}  # stamp -> keys with that stamp
        self._given: dict[int, int] = {}  # key -> index of the last update that stamped it
        self._recent: deque[list[int]] = deque()  # keys stamped in each of the last updates
        self._n_updates = 0
        # Constraint groups: CCOLAMD labels (absent: group 0), kept between updates and changed
        # where a key's group changed; rebuilt when the set of blocks or the fine depth changes.
        self._groups = gtsam.KeyGroupMap()
        self._label: dict[int, int] = {}
        self._labelled_blocks: tuple[float, ...] = ()
        self._labelled_fine = -1
        self._in_order = True
        self._held: set[int] = set()
        self._result: gtsam.ISAM2Result | None = None
        #: full re-eliminations made to restore the order before a marginalisation
        self.reorders = 0
        #: updates whose groups could not follow the blocks (ran unconstrained)
        self.unordered_updates = 0
        self.ballast = float(ballast)
        #: ballast variables in the smoother
        self.n_ballast = 0

    # -- the part of IncrementalFixedLagSmoother's interface the runner uses -------------------

    def update(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        stamps: dict[int, float],
        remove: list[int] | None = None,
    ) -> gtsam.ISAM2Result:
        """Add factors and values (``stamps``: marginalisation stamp of each new or refreshed
        key), remove factors by index, update iSAM2 and marginalise the keys older than the lag.

        Raises:
            ValueError: a new value without a stamp (it could never be marginalised).
            RuntimeError, IndexError, ValueError from GTSAM: the smoother is then unusable.
        """
        for key in values.keys():
            if key not in stamps and key not in self._stamp:
                raise ValueError(
                    f"TimeOrderedSmoother.update: new value {gtsam.DefaultKeyFormatter(key)} "
                    "has no stamp"
                )
        self._n_updates += 1
        observed = set(graph.keyVector()) if graph.size() else set()
        raised = self._restamp(stamps)
        # A key whose stamp grew without a new factor on it keeps its old place in the tree:
        # re-eliminate it (and its path to the root) so that it moves with its new group.
        extra_keys = [k for k in raised if k not in observed]
        fine = min(self.fine_levels, len(observed) - len(self._blocks))
        if self._blocks and fine >= 0:
            self._relabel(fine)
            groups = self._groups
        else:
            groups = None
            self._in_order = False
            self._labelled_blocks = ()  # relabel every key at the next ordered update
            self.unordered_updates += 1
        extra = _key_list(extra_keys) if extra_keys else None
        held = _key_list(self._held) if self._held else None
        if self.ballast > 0:
            graph, values = self._add_ballast(graph, values)
        self._result = self.isam.update(graph, values, list(remove or []), groups, held, extra)
        if remove:
            self._forget_unused()
        self._marginalize()
        return self._result

    def _add_ballast(
        self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values
    ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The update's factors and values with the ballast variables the window now needs
        (``ballast`` per window key, plus 2) appended; the caller's objects are not changed and
        the update's own factors keep their positions (``getNewFactorsIndices``)."""
        need = int(np.ceil(self.ballast * len(self._stamp))) + 2
        if need <= self.n_ballast:
            return graph, values
        g2 = gtsam.NonlinearFactorGraph()
        g2.push_back(graph)
        v2 = gtsam.Values(values)
        unit = gtsam.noiseModel.Unit.Create(1)
        for i in range(self.n_ballast, need):
            g2.add(gtsam.PriorFactorVector(BALLAST(i), np.zeros(1), unit))
            v2.insert(BALLAST(i), np.zeros(1))
        self.n_ballast = need
        return g2, v2

    def hold_linearization(self, keys) -> None:
        """Never relinearise these keys while they are in the window (iSAM2 does so for the keys
        of the marginal factors it creates; a window moved here from another smoother brings
        such factors without that knowledge)."""
        self._held.update(int(k) for k in keys)

    def calculateEstimatePose3(self, key: int) -> gtsam.Pose3:  # noqa: N802 (GTSAM's names)
        return self.isam.calculateEstimatePose3(key)

    def calculateEstimateVector(self, key: int) -> Any:  # noqa: N802
        return self.isam.calculateEstimateVector(key)

    def calculateEstimateConstantBias(self, key: int) -> Any:  # noqa: N802
        return self.isam.calculateEstimateConstantBias(key)

    def calculateEstimateSimilarity3(self, key: int) -> Any:  # noqa: N802
        return self.isam.calculateEstimateSimilarity3(key)

    def calculateEstimate(self) -> gtsam.Values:  # noqa: N802
        return self.isam.calculateEstimate()

    def marginalCovariance(self, key: int) -> Any:  # noqa: N802
        return self.isam.marginalCovariance(key)

    def marginalCovariances(self, keys: list[int]) -> list[np.ndarray]:  # noqa: N802
        """The marginal covariance of each of ``keys`` (their diagonal blocks of one joint
        marginal): one elimination of the window's Bayes tree for all of them instead of one per
        key (the newest keyframe's pose and velocity sit in the root clique: about half the
        time of two ``marginalCovariance`` calls; the same blocks to ~1e-9 relative)."""
        jm = self.isam.jointMarginalCovariance(list(keys))
        return [np.asarray(jm.at(k, k)) for k in keys]

    def getFactors(self) -> gtsam.NonlinearFactorGraph:  # noqa: N802
        return self.isam.getFactorsUnsafe()

    def getLinearizationPoint(self) -> gtsam.Values:  # noqa: N802
        return self.isam.getLinearizationPoint()

    def getISAM2Result(self) -> gtsam.ISAM2Result:  # noqa: N802
        if self._result is None:
            raise RuntimeError("TimeOrderedSmoother: no update yet")
        return self._result

    def timestamps(self) -> dict[int, float]:
        return dict(self._stamp)

    def __contains__(self, key: int) -> bool:
        """Is ``key`` in the window (not marginalised)?"""
        return key in self._stamp

    # -- ordering ------------------------------------------------------------------------------

    def _restamp(self, stamps: dict[int, float]) -> list[int]:
        """Record the stamps; returns the keys already in the window whose stamp grew. A stamp
        that decreases takes its key out of time order: the window is re-ordered before the
        next marginalisation."""
        u = self._n_updates
        raised = []
        for key, t in stamps.items():
            t = float(t)
            old = self._stamp.get(key)
            if old != t:
                if old is not None:
                    self._leave_block(key, old)
                    if t > old:
                        raised.append(key)
                    else:
                        self._in_order = False
                self._stamp[key] = t
                self._blocks.setdefault(t, set()).add(key)
            self._given[key] = u
        self._recent.append(list(stamps))
        while len(self._recent) > self.fine_levels + 1:
            self._recent.popleft()
        return raised

    def _forget_unused(self) -> None:
        """Drop the keys iSAM2 removed (all their factors were removed) from the bookkeeping."""
        for key in [k for k in self._stamp if not self.isam.valueExists(k)]:
            self._leave_block(key, self._stamp.pop(key))
            self._given.pop(key, None)
            self._held.discard(key)
            if self._label.pop(key, 0):
                self._groups.erase(key)

    def _leave_block(self, key: int, t: float) -> None:
        keys = self._blocks[t]
        keys.discard(key)
        if not keys:
            del self._blocks[t]

    def _relabel(self, fine: int) -> None:
        """Bring the constraint groups up to date. A key's label is the rank of its stamp block;
        in the newest block, plus one level per update among the last ``fine`` (newest
        highest). Labels stay below ``len(blocks) + fine`` (CCOLAMD needs them below the number
        of re-eliminated variables, at least the keys of the new factors). Between changes of
        the block set only the keys stamped in the last updates change label."""
        blocks = tuple(sorted(self._blocks))
        rank = {b: i for i, b in enumerate(blocks)}
        top = len(blocks) - 1
        u = self._n_updates
        given = self._given

        def level(key: int, t: float) -> int:
            lvl = rank[t]
            return lvl + max(0, fine - (u - given[key])) if lvl == top else lvl

        if blocks != self._labelled_blocks or fine != self._labelled_fine:
            # Every key afresh (the labels are empty: each nonzero level is inserted): one pass
            # over the stamps without the lookups of the incremental path (twice a second on
            # the 180 s benchmark, ~200 keys each; 2026-12-07).
            self._groups.clear()
            self._label = label = {}
            self._labelled_blocks, self._labelled_fine = blocks, fine
            insert2 = self._groups.insert2
            for key, t in self._stamp.items():
                lvl = level(key, t)
                if lvl:
                    insert2(key, lvl)
                    label[key] = lvl
            return
        keys = {k for batch in self._recent for k in batch}
        stamp, label, groups = self._stamp, self._label, self._groups
        t_top = blocks[top]
        for key in keys:
            t = stamp.get(key)
            if t is None:  # marginalised since
                continue
            # (level() written out: this loop runs for ~20 keys at every update)
            lvl = top + max(0, fine - (u - given[key])) if t == t_top else rank[t]
            was = label.get(key, 0)
            if was != lvl:
                if was:  # KeyGroupMap.insert2 does not overwrite
                    groups.erase(key)
                if lvl:
                    groups.insert2(key, lvl)
                    label[key] = lvl
                else:
                    del label[key]

    def _marginalize(self) -> None:
        if not self._blocks:
            return
        cut = max(self._blocks) - self.lag_s
        old = [b for b in self._blocks if b < cut]
        if not old:
            return
        if not self._in_order:
            self._reorder()
        gone = [k for b in old for k in self._blocks[b]]
        first = self._split_cliques_first(gone)
        for batch in (first, [k for k in gone if k not in first] if first else gone):
            if batch:
                self.isam.marginalizeLeaves(_key_list(batch))
        for b in old:
            del self._blocks[b]
        for k in gone:
            del self._stamp[k]
            self._given.pop(k, None)
            self._held.discard(k)
            if self._label.pop(k, 0):
                self._groups.erase(k)

    def _split_cliques_first(self, gone: list[int]) -> set[int]:
        """Keys to marginalise in a first ``marginalizeLeaves`` call: those of the cliques that
        keep some of their keys, with the subtrees that depend on them. In one call, GTSAM 4.3
        climbs from a marginalised leaf clique to a parent whose first key is marginalised, splits
        that parent and never removes the leaf clique when its separator does not hold the
        parent's marginalised keys ("Asking to remove variables from the variable index that are
        not unused"; found by the fuzz test). Split cliques first, the rest in a second call.

        Raises:
            RuntimeError: keys to marginalise that do not lead their clique (the time order is
                broken: iSAM2 would corrupt its tree).
        """
        return split_cliques(self.isam.dot(str), gone)

    def _reorder(self) -> None:
        """Re-eliminate the whole window with the block groups (the tree then follows the
        stamps again)."""
        self._labelled_blocks = ()
        self._relabel(0)
        # (the update's own result, with its new factor indices, stays the one reported)
        empty = gtsam.NonlinearFactorGraph()
        self.isam.update(empty, gtsam.Values(), [], self._groups, None, _key_list(self._stamp))
        self._in_order = True
        self.reorders += 1


def move_window(old: Any, new: Any) -> dict[int, int]:
    """Move a fixed-lag window into a fresh smoother ``new`` (``TimeOrderedSmoother`` or
    ``IncrementalFixedLagSmoother``) losslessly: the same factors at the same linearisation point
    and stamps. Marginals (``LinearContainerFactor``) are anchored at their linearisation point and
    their variables held there, as the old iSAM2 held them. Works on a smoother whose update just
    failed (its factors include that update's). Ballast variables (``BALLAST``) stay behind.

    Returns:
        factor index in ``old`` -> index in ``new``.

    Raises:
        RuntimeError, IndexError, ValueError from GTSAM when ``new`` fails too.
    """
    factors = old.getFactors()
    lin_point = old.getLinearizationPoint()
    ballast = [k for k in lin_point.keys() if is_ballast(k)]
    if ballast:  # the new smoother makes its own (a copy: the point may be iSAM2's own)
        lin_point = gtsam.Values(lin_point)
        for k in ballast:
            lin_point.erase(k)
    graph = gtsam.NonlinearFactorGraph()
    index: dict[int, int] = {}
    held: set[int] = set()
    for i in range(factors.size()):
        f = factors.at(i)
        if f is None or (f.size() == 1 and is_ballast(f.keys()[0])):
            continue
        if isinstance(f, gtsam.LinearContainerFactor):
            held.update(f.keys())
            f = gtsam.LinearContainerFactor(f.linearize(lin_point), lin_point)
        index[i] = graph.size()
        graph.add(f)
    if held and isinstance(new, TimeOrderedSmoother):
        new.hold_linearization(held)
    new.update(graph, lin_point, old.timestamps())
    return index
