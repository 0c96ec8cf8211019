"""
Contact relation recognition under pose noise, frame by frame and over a track.

Detecting the relation with one distance tolerance fails on real stereo poses (errors of a few
millimetres and degrees): a tight tolerance misses contacts, a wide one takes every element
near the other object as a contact. Here the relation is *selected*, as a model:

1. **Pool**: every element pair within ``search_margin`` of contact at the observed pose
   (:func:`~contact_correction.contact_relation.detect_contact_relation` with the margin as
   separation, penetration and element tolerance).
2. **Groups**: the pool's pairs are grouped into contact primitives that are on or off
   together: all pairs of one face of the moving object lying against one face of the fixed
   object (opposite normals: a face-face contact, with its vertex-face, face-vertex and
   edge-edge pairs), an edge lying on a face, and single vertex-face / face-vertex / edge-edge
   contacts. A group key names elements only, so it is the same in every frame of a track.
3. **Score** of a candidate relation S (a set of groups), from the stated pose noise
   (``sigma_translation`` [m] at the moving object's origin, ``sigma_rotation`` [rad]): to
   first order (Eq. 2's rows ``a_k``, distances ``d_k``), the smallest correction that brings
   every pair of S to contact has the Mahalanobis size
   ``chi2(S) = d_S^T (A_S Sigma A_S^T + sigma_model^2 I)^-1 d_S``; pairs outside S that this
   correction would push into penetration are added as active constraints (the relation says
   "not in contact", i.e. ">= 0") and their cost counted. The score is
   ``chi2(S) + free_dof_penalty * (6 - rank(S))``: each degree of freedom the relation leaves
   free costs a fixed penalty (an information criterion: a relation with more free parameters
   explains any observation; the BIC-like penalty is ``2 ln(range / (sqrt(2 pi) sigma))`` for a
   gap uniformly distributed over ``range`` when not in contact), so a contact is kept when the
   correction it needs is small against the noise and dropped when it is not.
   A face-face group counts only when its faces share an area at the relation's corrected
   pose (``area_contact_check``): two faces that meet only along a boundary (a T-peg's back
   face level with the slotted block's front face at the slot's entrance, the peg's profile
   fitting the slot's) are within the noise of contact at the boundary, yet nothing stops
   the peg along their normal.
4. **Search**: greedy toggling of single groups from the best ``climbs`` of the starting
   relations (the temporal model's states, all groups, no group), evaluating a few dozen
   candidates per frame; with the area check, also from the best area-contact relation nested
   in the frame's best-scoring one when that one is not an area contact; offline, a second
   pass also scores at each frame the relations the first pass kept at the next ``lookahead``
   frames.
5. **Temporal model** (:class:`RelationTracker`): contact states change rarely. A Viterbi
   recursion over the candidate relations of consecutive frames, with a cost
   ``transition_cost`` per change of state plus ``switch_cost`` per group switched on or off
   between frames (a Markov chain over contact states; ``-2 ln`` of the switching
   probability), selects the relation sequence of least
   total cost. Online (node) the current best path's end is used, which gives hysteresis;
   offline (:func:`recognise_track`) the whole sequence is back-tracked.
6. **Online checks of the choice** (:meth:`RelationTracker.update`, the frame's output only,
   the paths unchanged): the safe rule (only the groups common with a nearby relation with
   fewer constraints that fits better), the evidence rule on the frame's chi2 and, with
   ``noise_correlation``, on the innovation chi2 (:meth:`RelationTracker.innovation_check`),
   and the area check of the chosen relation's face-face groups
   (:meth:`RelationRecognizer.boundary_groups`). Each returns a subset of the chosen relation.

All quantities are in the fixed object's model frame, metres and radians.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import compress
import math
from typing import Dict, FrozenSet, Hashable, List, Optional, Sequence, Tuple

import numpy as np
from stereo_manip_tools.transforms import rotation_about_axis

from .contact_relation import (
    ContactPair, detect_contact_relation, EDGE, evaluate_contacts, FACE, relative_pose, VERTEX)
from .polyhedron import cross3, Polyhedron
from .small_linalg import eigvalsh, solve

__all__ = ['RecognitionOptions', 'Hypothesis', 'FrameCandidates', 'RelationRecognizer',
           'RelationTracker', 'recognise_track', 'group_key', 'common_state',
           'overlap_depth_2d']

GroupKey = Tuple[Hashable, ...]
State = FrozenSet[GroupKey]


@dataclass
class RecognitionOptions:
    """
    Parameters of relation recognition (see the module docstring).

    :ivar sigma_translation: stated pose noise, translation of the moving origin [m] (1 sigma).
    :ivar sigma_rotation: stated pose noise, rotation [rad] (1 sigma).
    :ivar sigma_model: model / linearisation error added to every contact distance [m].
    :ivar search_margin: pool margin [m]; None = 3 (sigma_t + sigma_r * size / 2).
    :ivar free_dof_penalty: score cost of each degree of freedom left free (3: chosen on the
        synthetic tracks of :mod:`.tracks` with another noise seed than the benchmark's; the
        BIC-like value ``2 ln(range / (sqrt(2 pi) sigma))`` is 2-4 for gaps over a
        centimetre at millimetre noise); None = ``max(2, 2 ln(search_margin /
        (sqrt(2 pi) sigma_t)) + 2)``.
    :ivar switch_cost: score cost per group switched on or off between consecutive frames
        (on top of ``transition_cost``).
    :ivar transition_cost: score cost of a change of contact state between consecutive frames,
        once per change (``-2 ln`` of the probability that the contact formation changes at a
        frame). A change of formation is one event even when several groups switch at once (a
        T-peg entering its slot: both shoulders and both stem walls cost 80 at ``switch_cost``
        20 per group, and the formation is recognised frames late). Total cost of ``a -> b``:
        ``transition_cost + switch_cost * |a ^ b|`` (0 when ``a == b``). ``switch_cost`` 5
        with ``transition_cost`` 15 (was 20 per group, no transition cost: one group switched
        costs 20 as before, four 35 instead of 80): on the benchmark the relation-right
        fraction went 0.978 / 0.984 -> 0.981 / 0.985 offline and 0.968 / 0.963 -> 0.974 /
        0.969 online (seed default / 7; 20 with 5 gave 0.972 / 0.966 online and held a
        single released contact a frame longer).
    :ivar area_contact_check: a face-face group is a contact only when its faces share an area
        at the relation's corrected pose (:meth:`RelationRecognizer.supported`); relations
        with a face-face group whose faces meet only along a boundary there are not chosen.
        Offline only (:func:`recognise_track` with ``smooth``): measured on the benchmark
        (both noise seeds) it raised the offline relation-right fraction (0.977 / 0.978 ->
        0.978 / 0.984 with ``lookahead`` and ``climbs``) but online it lowered it (0.963 ->
        0.959 on seed 7), let 2.1 mm of penetration through on one frame and doubled the
        recognition's CPU time: online the relation with the spurious flush face carries the
        right in-slot contacts into the formation sooner (the correction then drops the
        boundary-only group at the corrected pose), offline the back-tracking finds them
        without it. Online the check is made on the chosen relation only, after the temporal
        model (the paths unchanged): its face-face groups whose faces share no area are
        dropped from that frame's output (:meth:`RelationRecognizer.boundary_groups`; a
        T-peg entering its slot taken against the block's front face: 1.2-1.9 mm along the
        slot before).
    :ivar lookahead: offline (:func:`recognise_track` with ``smooth``), a second forward pass
        in which each frame also scores the relations kept in the temporal model's beams of
        the next ``lookahead`` frames of the first pass (a formation entered with little
        evidence, a T-peg 1.5 mm into its slot, is often not among the search's best at its
        first frames: the back-tracking could not choose it there). 0: one pass.
    :ivar climbs: greedy searches per frame, from the best ``climbs`` of the starting
        relations (no contact, every group, the temporal model's states); 1 searched from the
        best start only (a local optimum: at the slot's entrance, the relation with the
        block's front face held from the previous frame, the in-slot one three toggles away).
        With the area check (offline, fixed-lag) one more climb starts from the best area
        contact nested in the frame's best-scoring relation when that is not an area contact.
    :ivar angle_tolerance: angular slack of the pool's local tests and of the face-against-face
        grouping [rad]; None = max(0.1, 4 sigma_r).
    :ivar beam: relations kept per frame by the temporal model (the cheapest paths; offline
        also the relation explaining the frame best at each rank, whose path may be dearer
        there because a contact change pays its transition cost at its first frame).
    :ivar ambiguity_margin: offline safe rule at contact changes: when a relation with fewer
        constraints than the Viterbi one explains a frame better (chi2 lower by more than
        ``AMBIGUITY_FIT``) and its min-marginal (least total cost over the whole track of a
        sequence through it at that frame) is within this margin of the Viterbi path's, only
        the groups common to both are enforced there (a correction right under either
        relation: no direction that one of them leaves free is constrained). 0 disables it.
        Online (:meth:`RelationTracker.update`) the forward costs take the min-marginals'
        place, and the rule applies only when some group is common; online too, a relation
        with more constraints that scores better by more than one free DOF's penalty and is
        within this margin is used for the frame (:meth:`RelationTracker._onset_check`).
    :ivar evidence_chi2: the frame's evidence against the temporal model: when a relation
        nested in the chosen one (a subset of its groups, lower rank) explains the frame better
        by more than this chi2 per constraint it drops, the nested relation is used (a
        likelihood-ratio test: 9 = 3 sigma for one constraint). The temporal prior (the
        switch cost) may keep a relation over frames that fit it a little worse, never one
        that the frame rejects at 3 sigma (e.g. a peg entering a hole kept on the top face by
        hysteresis: its correction moved the peg 4-5 mm back up along the free direction).
        Online only (:meth:`RelationTracker.update`: the node, ``--online``): offline the
        Viterbi back-tracking sees the frames that follow and keeps a contact through an
        outlier frame. With ``noise_correlation`` > 0 the same test is also made on the
        innovation chi2 (:meth:`RelationTracker.innovation_check`: a contact held after its
        release needs a correction that jumps between frames). 0 disables both.
    :ivar max_correction_sigma: the correction-size guard ``k``: a correction whose
        translation of the moving origin exceeds ``k sigma_translation`` or whose rotation
        exceeds ``k sigma_rotation`` is far beyond the stated pose noise and is not applied
        blindly: the relations nested in it (fewer constraints), then the non-penetration
        only correction (push-out), are tried, and the result is flagged (``guarded``). 4: a
        3-D error of the stated per-axis noise is above 4 sigma with probability 0.1 %.
        0 disables it.
    :ivar noise_correlation: frame-to-frame correlation ``rho`` of the pose errors (a tracker
        that starts from its previous pose makes them AR(1): ``n_k = rho n_(k-1) + e_k``).
        With ``rho`` > 0 the temporal model scores a relation held from the previous frame by
        the *innovation* of its noise estimate, ``|delta_k - rho delta_(k-1)|^2 / (1 -
        rho^2)`` in place of ``|delta_k|^2`` (the exact AR(1) likelihood; chi-square with the
        same degrees of freedom when the relation is right): a contact held after its release
        needs a correction that jumps from one frame to the next (a peg lifted 2.2 mm per
        frame: innovation 4 sigma at rho 0.85), which the frame-by-frame chi2 cannot tell
        from a 2-sigma error. In the path costs offline only (:func:`recognise_track` with
        ``smooth``, the command without ``--online``): online, a wrong relation entered at
        the first frames with a steady offset pays only ``(1 - rho) / (1 + rho)`` of its chi2
        per frame (1/12 at 0.85) and was held longer (measured on the benchmark: online
        relation right 0.960 -> 0.946 on the held-out seed), while the back-tracking sees the
        frames after it. Online the innovation serves as evidence only: the evidence rule's
        test on it (at ``innovation_evidence_chi2``'s level,
        :meth:`RelationTracker.innovation_check`) drops, for that frame's output, a contact
        that the change since the previous frame rejects (benchmark, seed default / 7: online
        relation right 0.974 / 0.969 -> 0.978 / 0.973). 0: independent errors (the
        frame-by-frame chi2).
    :ivar innovation_evidence_chi2: the level of that online innovation test, as
        ``evidence_chi2``'s (a one-constraint chi2; the same tail probability for more):
        6.63 = p 0.01, looser than the frame's 3 sigma because its errors cost unequally. A
        false alarm costs one frame its correction (the nested relation is that frame's
        output only; the paths of the temporal model are unchanged); a miss makes the output
        worse than observed: a contact held after its release pulls the part back by the
        distance it has moved (a T-peg lifted 2.2 mm per frame at sigma 1.5 mm: innovation
        2.8 sigma). Benchmark, eleven noise draws, online, 9 -> 6.63: frames worse than
        observed by more than the stated noise 30 -> 22, relation right in contact 0.9768 ->
        0.9771 (mean), frames worse 1.64 -> 1.51 %, the constrained-error reduction's median
        8.5 -> 7.7 (a held contact dropped in a frame whose noise mimics a release). 0
        disables the test.
    """

    sigma_translation: float = 0.001
    sigma_rotation: float = float(np.deg2rad(1.0))
    sigma_model: float = 2e-4
    search_margin: Optional[float] = None
    free_dof_penalty: Optional[float] = 3.0
    switch_cost: float = 5.0
    angle_tolerance: Optional[float] = None
    beam: int = 6
    ambiguity_margin: float = 5.0
    evidence_chi2: float = 9.0
    innovation_evidence_chi2: float = 6.63
    max_correction_sigma: float = 4.0
    noise_correlation: float = 0.0
    transition_cost: float = 15.0
    area_contact_check: bool = True
    lookahead: int = 5
    climbs: int = 3

    def validate(self) -> None:
        """
        Check every value of the options.

        :raises ValueError: on a non-finite or out-of-range value, naming it.
        """
        for name in ('sigma_translation', 'sigma_rotation', 'sigma_model', 'switch_cost',
                     'transition_cost', 'ambiguity_margin', 'evidence_chi2',
                     'innovation_evidence_chi2', 'max_correction_sigma'):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise ValueError(f'{name} must be a finite number >= 0, got {v}')
        if self.sigma_translation <= 0 or self.sigma_rotation <= 0:
            raise ValueError('sigma_translation and sigma_rotation must be > 0')
        for name in ('search_margin', 'free_dof_penalty', 'angle_tolerance'):
            v = getattr(self, name)
            if v is not None and (not np.isfinite(v) or v < 0):
                raise ValueError(f'{name} must be a finite number >= 0 (or unset), got {v}')
        if int(self.beam) < 1:
            raise ValueError(f'beam must be >= 1, got {self.beam}')
        if int(self.climbs) < 1 or int(self.lookahead) < 0:
            raise ValueError(f'climbs must be >= 1 and lookahead >= 0, got {self.climbs}, '
                             f'{self.lookahead}')
        if not (np.isfinite(self.noise_correlation) and 0.0 <= self.noise_correlation < 1.0):
            raise ValueError('noise_correlation must be a finite number in [0, 1), got '
                             f'{self.noise_correlation}')

    def margin(self, moving: Polyhedron) -> float:
        """Return the pool margin [m] for ``moving``."""
        if self.search_margin is not None:
            return float(self.search_margin)
        return 3.0 * (self.sigma_translation + self.sigma_rotation * moving.size / 2.0)

    def penalty(self, moving: Polyhedron) -> float:
        """Return the per-free-DOF penalty."""
        if self.free_dof_penalty is not None:
            return float(self.free_dof_penalty)
        r = self.margin(moving) / (np.sqrt(2.0 * np.pi) * self.sigma_translation)
        return float(max(2.0, 2.0 * np.log(max(r, 1.0)) + 2.0))

    def angle(self) -> float:
        """Angular slack [rad]."""
        if self.angle_tolerance is not None:
            return float(self.angle_tolerance)
        return float(max(0.1, 4.0 * self.sigma_rotation))


@dataclass
class Hypothesis:
    """
    One candidate relation of a frame.

    :ivar state: its group keys.
    :ivar pairs: its pairs (from the frame's pool).
    :ivar chi2: Mahalanobis size of the first-order correction it needs.
    :ivar rank: constraint rank of Eq. 2 for its pairs.
    :ivar score: ``chi2 + penalty * (6 - rank)``.
    :ivar pushed: pairs outside the relation that the correction had to keep out of
        penetration.
    :ivar delta: the first-order correction (6,) in stated-noise units (rotation then
        translation of the moving origin, fixed frame, each divided by its sigma); the noise
        estimate under the relation is ``-delta`` (None: not scored). ``chi2 = |delta|^2 +``
        the contact residual left by the rigid correction.
    :ivar supported: every face-face group of it is an area contact at its corrected pose
        (:meth:`RelationRecognizer.supported`; None: not checked yet).
    """

    state: State
    pairs: Tuple[ContactPair, ...]
    chi2: float
    rank: int
    score: float
    pushed: int = 0
    delta: Optional[np.ndarray] = None
    supported: Optional[bool] = None


@dataclass
class FrameCandidates:
    """The pool, its groups and the candidate relations evaluated for one frame."""

    pool: List[ContactPair]
    groups: Dict[GroupKey, np.ndarray]
    hypotheses: Dict[State, Hypothesis] = field(default_factory=dict)
    best: Optional[Hypothesis] = None

    def ranked(self) -> List[Hypothesis]:
        """Hypotheses, best (lowest score) first (unscored ones last)."""
        return sorted(self.hypotheses.values(),
                      key=lambda h: h.score if np.isfinite(h.score) else float('inf'))

    def hypothesis(self, state: State) -> Hypothesis:
        """
        Return the frame's hypothesis for ``state``.

        ``state`` is a set of the frame's groups; a hypothesis not scored in the search is
        built unscored (``chi2``, ``score`` nan, ``rank`` -1).
        """
        h = self.hypotheses.get(state)
        if h is not None:
            return h
        mask = np.zeros(len(self.pool), dtype=bool)
        for k in state:
            mask[self.groups[k]] = True
        return Hypothesis(state, tuple(p for p, m in zip(self.pool, mask) if m),
                          float('nan'), -1, float('nan'))


#: slack, in units of sigma_translation, of the guard's nearest-exit test: a vertex inside the
#: other solid penetrates a face only when that face is no farther than the nearest surface
#: plus this slack (was 1.5: a peg corner entering a zero-clearance hole, pushed 0.5-1.6 mm
#: into the wall by the noise and 2.8 mm below the top face, took the top face as its exit and
#: the relation's correction lifted the peg by the insertion depth)
EXIT_SLACK = 0.5

_EYE6 = np.eye(6)

#: shift [sigma_translation] along a relation's free translations within which a face-face
#: group's faces must come to share an area (:meth:`RelationRecognizer.supported`)
FREE_SHIFT_SIGMA = 2.0

#: chi2 by which a relation with fewer constraints must explain a frame better than the chosen
#: one to make it ambiguous (the data favour it, only the priors do not)
AMBIGUITY_FIT = 1.0


def chi2_survival(x: float, dof: int) -> float:
    """P(X > x) for X chi-square distributed with integer ``dof`` >= 1 degrees of freedom."""
    x = max(float(x), 0.0)
    h = x / 2.0
    if dof % 2 == 0:
        term, total = 1.0, 1.0
        for i in range(1, dof // 2):
            term *= h / i
            total += term
        return float(np.exp(-h) * total)
    total = math.erfc(math.sqrt(h))
    for i in range((dof - 1) // 2):
        total += math.exp(-h + (i + 0.5) * math.log(h) - math.lgamma(i + 1.5)) if h > 0 else 0.0
    return float(total)


def chi2_threshold(chi2_one_dof: float, dof: int) -> float:
    """
    Return the chi-square quantile for ``dof`` at the tail probability of ``chi2_one_dof``.

    The tail probability is that of ``chi2_one_dof`` with one degree of freedom (e.g. 9 ->
    p 0.0027 -> 11.8 for 2 dof, 14.2 for 3).
    """
    p = chi2_survival(chi2_one_dof, 1)
    lo, hi = 0.0, max(chi2_one_dof, 1.0) * (dof + 2.0) + 50.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if chi2_survival(mid, dof) > p:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def common_state(states: Sequence[State]) -> State:
    """Return the groups common to every state (the relation right under any of them)."""
    out = frozenset(states[0])
    for s in states[1:]:
        out &= s
    return out


def _faces_of_edge(poly: Polyhedron, e: int) -> np.ndarray:
    return poly.edge_faces[e]


def _edge_normals_2d(tris: np.ndarray) -> np.ndarray:
    """Return the unit normals (k, 3, 2) of the edges of 2-D triangles (k, 3, 2)."""
    e = np.roll(tris, -1, axis=1) - tris
    n = np.stack([-e[..., 1], e[..., 0]], axis=-1)
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)


def _overlap_depth_2d_numpy(A: np.ndarray, B: np.ndarray) -> float:
    """:func:`overlap_depth_2d` in numpy (the reference of the compiled kernel)."""
    na, nb = _edge_normals_2d(A), _edge_normals_2d(B)
    pa = np.einsum('iad,ipd->iap', na, A)               # A_i on its own axes (ka, 3, 3)
    pba = np.einsum('iad,jpd->ijap', na, B)             # B_j on A_i's axes (ka, kb, 3, 3)
    ov_a = (np.minimum(pa.max(-1)[:, None], pba.max(-1))
            - np.maximum(pa.min(-1)[:, None], pba.min(-1)))
    pb = np.einsum('jad,jpd->jap', nb, B)
    pab = np.einsum('jad,ipd->ijap', nb, A)
    ov_b = (np.minimum(pb.max(-1)[None], pab.max(-1))
            - np.maximum(pb.min(-1)[None], pab.min(-1)))
    return float(np.minimum(ov_a.min(-1), ov_b.min(-1)).max())


try:
    import numba

    @numba.njit(cache=True, fastmath=False)
    def _axis_overlap(P: np.ndarray, Q: np.ndarray, i: int, j: int, a: int) -> float:
        """Overlap of triangles P[i] and Q[j] along the normal of P[i]'s edge a."""
        b = (a + 1) % 3
        ex, ey = P[i, b, 0] - P[i, a, 0], P[i, b, 1] - P[i, a, 1]
        nx, ny = -ey, ex
        ln = np.sqrt(nx * nx + ny * ny)
        if ln < 1e-300:
            ln = 1e-300
        nx, ny = nx / ln, ny / ln
        p_lo, p_hi, q_lo, q_hi = np.inf, -np.inf, np.inf, -np.inf
        for c in range(3):
            v = nx * P[i, c, 0] + ny * P[i, c, 1]
            p_lo, p_hi = min(p_lo, v), max(p_hi, v)
            w = nx * Q[j, c, 0] + ny * Q[j, c, 1]
            q_lo, q_hi = min(q_lo, w), max(q_hi, w)
        return min(p_hi, q_hi) - max(p_lo, q_lo)

    @numba.njit(cache=True, fastmath=False)
    def _overlap_depth_kernel(A: np.ndarray, B: np.ndarray) -> float:  # pragma: no cover
        """Compiled :func:`overlap_depth_2d`."""
        best = -np.inf
        for i in range(A.shape[0]):
            for j in range(B.shape[0]):
                depth = np.inf
                for a in range(3):
                    depth = min(depth, _axis_overlap(A, B, i, j, a),
                                _axis_overlap(B, A, j, i, a))
                best = max(best, depth)
        return best
except ImportError:  # pragma: no cover - numba is in the environment
    _overlap_depth_kernel = None


def overlap_depth_2d(A: np.ndarray, B: np.ndarray) -> float:
    """
    Depth [m] by which two unions of triangles of a plane overlap.

    The largest, over the pairs of a triangle of ``A`` (ka, 3, 2) and one of ``B`` (kb, 3, 2),
    of their penetration depth (separating-axis test on the six edge normals: the shortest
    shift that separates them, the width of their overlap across its narrowest direction).
    Positive when the regions share an area, 0 when they only touch along a boundary,
    negative when they are apart. Compiled with numba when it is installed (the numpy
    reference, ``_overlap_depth_2d_numpy``, gives the same depths to rounding).
    """
    if _overlap_depth_kernel is None or not len(A) or not len(B):
        return _overlap_depth_2d_numpy(A, B)
    return float(_overlap_depth_kernel(np.ascontiguousarray(A, dtype=float),
                                       np.ascontiguousarray(B, dtype=float)))


def group_key(moving: Polyhedron, fixed: Polyhedron, R: np.ndarray, pair: ContactPair,
              cos_tol: float) -> GroupKey:
    """
    Pose-independent key of the contact primitive ``pair`` belongs to.

    ``R`` rotates moving-model directions into the fixed frame (observed pose). A pair whose
    elements lie on a moving face and a fixed face with opposite normals (within the angular
    slack) belongs to that face-face contact ``('ff', g, f)``; a vertex-face pair whose vertex
    has an edge lying on the face belongs to the edge-face contact ``('ef', e, f)``; other pairs
    are their own group.
    """
    if pair.moving_type == VERTEX and pair.fixed_type == FACE:
        v, f = pair.moving_index, pair.fixed_index
        nf = fixed.face_normals[f]
        faces = moving.vertex_faces[v]
        c = (moving.face_normals[faces] @ R.T) @ nf
        k = int(np.argmin(c))
        if c[k] < -cos_tol:
            return ('ff', int(faces[k]), f)
        d = (moving.vertex_edge_dirs[v] @ R.T) @ nf
        on = np.flatnonzero(np.abs(d) < np.sqrt(max(0.0, 1.0 - cos_tol ** 2)))
        if len(on) == 1:
            return ('ef', int(moving.vertex_edges[v][on[0]]), f)
        return ('vf', v, f)
    if pair.moving_type == FACE and pair.fixed_type == VERTEX:
        g, w = pair.moving_index, pair.fixed_index
        ng = R @ moving.face_normals[g]
        faces = fixed.vertex_faces[w]
        c = fixed.face_normals[faces] @ ng
        k = int(np.argmin(c))
        if c[k] < -cos_tol:
            return ('ff', g, int(faces[k]))
        return ('fv', g, w)
    if pair.moving_type == EDGE and pair.fixed_type == EDGE:
        gm = _faces_of_edge(moving, pair.moving_index)
        gf = _faces_of_edge(fixed, pair.fixed_index)
        c = (moving.face_normals[gm] @ R.T) @ fixed.face_normals[gf].T       # (2, 2)
        i, j = np.unravel_index(int(np.argmin(c)), c.shape)
        if c[i, j] < -cos_tol:
            return ('ff', int(gm[i]), int(gf[j]))
        em = R @ moving.edge_directions[pair.moving_index]
        for f in gf:     # the moving edge lying on a face of the fixed edge: edge-face
            if abs(em @ fixed.face_normals[f]) < np.sqrt(max(0.0, 1.0 - cos_tol ** 2)):
                return ('ef', pair.moving_index, int(f))
        return ('ee', pair.moving_index, pair.fixed_index)
    return ('other', pair.moving_type, pair.moving_index, pair.fixed_type, pair.fixed_index)


class RelationRecognizer:
    """
    Per-frame candidate relations and their scores (see the module docstring).

    :param moving: moving object's polyhedron.
    :param fixed: fixed object's polyhedron.
    :param options: noise model and search parameters.
    """

    def __init__(self, moving: Polyhedron, fixed: Polyhedron,
                 options: Optional[RecognitionOptions] = None) -> None:
        self.moving, self.fixed = moving, fixed
        self._guard = np.zeros(0, dtype=bool)
        self.options = options or RecognitionOptions()
        self.options.validate()
        self.margin = self.options.margin(moving)
        self.penalty = self.options.penalty(moving)
        self.angle = self.options.angle()
        self.cos_tol = float(np.cos(self.angle))
        o = self.options
        self._w = np.array([o.sigma_rotation] * 3 + [o.sigma_translation] * 3)
        # chi2 decreases that reject 1..6 dropped constraints at each test's level (inf: off)
        self._evidence, self._innovation = (
            {k: chi2_threshold(level, k) if level > 0 else float('inf') for k in range(1, 7)}
            for level in (o.evidence_chi2, o.innovation_evidence_chi2))
        self._plane_tris: Dict[int, Tuple[np.ndarray, np.ndarray]] = {}
        #: the area-contact check is on (``area_contact_check``, offline: set by
        #: :func:`recognise_track` with ``smooth``)
        self.area_check = False
        self._T_rel = np.eye(4)

    # --- one frame -------------------------------------------------------------------------

    def frame(self, T_moving: np.ndarray, T_fixed: np.ndarray,
              seeds: Sequence[State] = ()) -> FrameCandidates:
        """
        Pool, groups and the greedy search of the best relation at one observed pose.

        :param seeds: relations to start the search from and to score in any case (e.g. the
            temporal model's current states).
        """
        self._previous = self._context()
        T_rel = relative_pose(T_moving, T_fixed)
        self._T_rel = T_rel
        pool = detect_contact_relation(self.moving, self.fixed, T_moving, T_fixed,
                                       tolerance=self.margin,
                                       penetration_tolerance=self.margin,
                                       angle_tolerance=self.angle)
        R = T_rel[:3, :3]
        keys = [group_key(self.moving, self.fixed, R, p, self.cos_tol) for p in pool]
        groups: Dict[GroupKey, List[int]] = {}
        for k, key in enumerate(keys):
            groups.setdefault(key, []).append(k)
        fc = FrameCandidates(pool, {k: np.asarray(v) for k, v in groups.items()})
        if pool:
            g = evaluate_contacts(self.moving, self.fixed, T_rel, pool)
            c = T_rel[:3, 3]
            A = np.hstack([cross3(g.points - c, g.normals), g.normals])
            self._A = A * self._w          # whitened: noise of unit variance per column
            self._d = g.distances
            self._guard = self._guarded(T_rel, pool, g.distances)
            self._P = self._A[:, :, None] * self._A[:, None, :]
            # rank rows: in a face-face group every pair constrains along the fixed face's
            # normal (the moving face's normal, tilted by the pose error, would add a spurious
            # weak constraint within the face's plane)
            Nc = g.normals.copy()
            for key, idx in fc.groups.items():
                if key[0] == 'ff':
                    Nc[idx] = self.fixed.face_normals[key[2]]
            Ac = np.hstack([cross3(g.points - c, Nc), Nc]) * self._w
            Pc = Ac[:, :, None] * Ac[:, None, :]
            self._gsum = {}
            for key, idx in fc.groups.items():
                Ai, di = self._A[idx], self._d[idx]
                self._gsum[key] = (self._P[idx].sum(0), Ai.T @ di, float(di @ di),
                                   Pc[idx].sum(0))
        else:
            self._A = np.zeros((0, 6))
            self._d = np.zeros(0)
            self._guard = np.zeros(0, dtype=bool)
        self._fc = fc
        empty: State = frozenset()
        starts = [self.evaluate(empty), self.evaluate(frozenset(fc.groups))]
        for s in seeds:
            h = self.evaluate(frozenset(s))
            if h is not None:
                starts.append(h)
        for h in [h for h in sorted(starts, key=lambda h: h.score)
                  if self.supported(h)][:self.options.climbs]:
            self._climb(h)
        if self.area_check:
            # the climbs step through area contacts only: where the frame's best relation is
            # not one, the area contacts nested in it may be out of their reach (the demo's peg
            # slid 0.9 mm off its hole's mouth onto the top face: every group, the walls it
            # left and its bottom on the top face, scored best and met only along the rim;
            # the climbs from the walls held by the temporal model never reached the bottom
            # face alone, and the fixed-lag output pulled the peg back onto the hole's axis,
            # ADD-sym 0.17 -> 0.92 mm)
            top = min(fc.hypotheses.values(), key=lambda h: h.score)
            if not self.supported(top):
                for h in self.nested(top)[:1]:
                    self._climb(h)
        fc.best = min((h for h in fc.hypotheses.values() if h.supported),
                      key=lambda h: h.score, default=starts[0])
        return fc

    _CONTEXT = ('_fc', '_A', '_d', '_guard', '_P', '_gsum', '_T_rel')

    def _context(self) -> Optional[tuple]:
        """Return the current frame's scoring data (None before the first frame)."""
        if getattr(self, '_fc', None) is None:
            return None
        return tuple(getattr(self, n, None) for n in self._CONTEXT)

    def evaluate_previous(self, state: State) -> Optional[Hypothesis]:
        """
        Score ``state`` in the frame before the current one (None: not possible there).

        The temporal model's AR(1) noise model needs each relation's noise estimate of the
        previous frame, also for a relation that was not scored there.
        """
        prev = getattr(self, '_previous', None)
        if prev is None or prev[0] is None:
            return None
        if state in prev[0].hypotheses:
            return prev[0].hypotheses[state]
        if any(k not in prev[0].groups for k in state) or not prev[0].pool:
            return None
        cur = self._context()
        for n, v in zip(self._CONTEXT, prev):
            setattr(self, n, v)
        try:
            return self.evaluate(state)
        finally:
            for n, v in zip(self._CONTEXT, cur):
                setattr(self, n, v)

    def face_overlap(self, moving_face: int, fixed_face: int, T_rel: np.ndarray) -> float:
        """
        Overlap depth [m] of a moving face and a fixed face, in the fixed face's plane.

        :func:`overlap_depth_2d` of the two faces' triangles projected on the fixed face's
        plane, the moving one at ``T_rel`` (4x4, moving in the fixed frame).
        """
        basis_tris = self._plane_tris.get(fixed_face)
        if basis_tris is None:
            n = self.fixed.face_normals[fixed_face]
            u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
            u /= np.linalg.norm(u)
            basis = np.stack([u, np.cross(n, u)], axis=1)            # (3, 2)
            basis_tris = (basis, self.fixed._face_tris[fixed_face] @ basis)
            self._plane_tris[fixed_face] = basis_tris
        basis, fixed_2d = basis_tris
        moving_2d = (self.moving._face_tris[moving_face] @ T_rel[:3, :3].T + T_rel[:3, 3]) @ basis
        return overlap_depth_2d(moving_2d, fixed_2d)

    def supported(self, h: Hypothesis) -> bool:
        """
        Check that every face-face group of ``h`` is an area contact at its corrected pose.

        A face-face contact is one whose faces share an area: two faces whose regions meet
        only along a boundary line (a T-peg's back face level with the slotted block's front
        face: the peg's profile fits the slot's, the faces are complementary) do not stop the
        peg along their normal, yet their pairs at the boundary are within the noise of
        contact and would make the relation constrain a free direction. At the relation's
        first-order corrected pose (the observation moved by ``-delta`` in noise units: the
        other contacts of the relation brought to contact, the free coordinates as observed)
        the faces' overlap depth (:meth:`face_overlap`) must exceed ``sigma_model`` (the
        stated model / linearisation error), there or with the pose shifted by
        ``FREE_SHIFT_SIGMA`` sigma_translation along a translation the relation leaves free
        (the free coordinates are known only to the noise: a peg 1.5 mm into its slot,
        observed 2 mm out, is still in contact with the slot's walls; complementary faces
        overlap at no shift, their normal being constrained). Hypotheses of the current frame
        only (cached on ``h``); an unscored one (no correction) is taken as supported.
        """
        if h.supported is not None:
            return h.supported
        h.supported = not (self.area_check and self.boundary_groups(h, first_only=True))
        return h.supported

    def boundary_groups(self, h: Hypothesis, first_only: bool = False) -> State:
        """
        Return the face-face groups of ``h`` whose faces share no area (see :meth:`supported`).

        Computed whatever ``area_check`` says, at ``h``'s first-order corrected pose and with it
        shifted by ``FREE_SHIFT_SIGMA`` sigma_translation along ``h``'s free translations.
        A hypothesis of the current frame; an unscored one (no correction) has none.

        :param first_only: stop at the first such group (a yes / no answer).
        """
        keys = [k for k in h.state if k[0] == 'ff']
        if not keys or h.delta is None:
            return frozenset()
        w = h.delta[:3] * self.options.sigma_rotation
        v = h.delta[3:] * self.options.sigma_translation
        angle = float(np.linalg.norm(w))
        T = self._T_rel.copy()
        if angle > 0:
            T[:3, :3] = rotation_about_axis(w, angle) @ T[:3, :3]
        T[:3, 3] += v
        tol = self.options.sigma_model
        shifts = None
        out = set()
        for k in keys:
            if self.face_overlap(k[1], k[2], T) > tol:
                continue
            if shifts is None:
                shifts = [s * f for f in self._free_translations(h)
                          for s in (FREE_SHIFT_SIGMA * self.options.sigma_translation,
                                    -FREE_SHIFT_SIGMA * self.options.sigma_translation)]
            T_s = T.copy()
            for shift in shifts:
                T_s[:3, 3] = T[:3, 3] + shift
                if self.face_overlap(k[1], k[2], T_s) > tol:
                    break
            else:
                out.add(k)
                if first_only:
                    break
        return frozenset(out)

    def _free_translations(self, h: Hypothesis) -> np.ndarray:
        """
        Return the translations (rows, fixed frame, orthonormal) ``h``'s contacts leave free.

        The null space of its pairs' normals at the observed pose, every pair of a face-face
        group taking its fixed face's normal (as the rank does; the recognition's cached rows,
        where :func:`~contact_correction.trajectory._recognised_free_translation` evaluates
        the pairs again at a given pose).
        """
        rows = []
        for k in h.state:
            if k[0] == 'ff':
                rows.append(self.fixed.face_normals[k[2]][None])
            else:
                rows.append(self._A[self._fc.groups[k], 3:] / self.options.sigma_translation)
        if not rows:
            return np.eye(3)
        _, sv, Vt = np.linalg.svd(np.vstack(rows))
        return Vt[int(np.count_nonzero(sv > 1e-6 * max(1.0, sv[0]))):]

    def _guarded(self, T_rel: np.ndarray, pool: Sequence[ContactPair],
                 distances: np.ndarray) -> np.ndarray:
        """
        Pairs whose non-penetration a relation must respect when they are not part of it.

        a vertex near its face's region, on the outside, or inside the other solid with this face
        (within the noise) the nearest to it; edge-edge pairs (crossing on both edges). A vertex
        behind a face's plane but outside the solid (e.g. over the top face next to a hole wall) is
        not penetrating that face.
        """
        out = np.ones(len(pool), dtype=bool)
        tol = EXIT_SLACK * self.options.sigma_translation
        R, t = T_rel[:3, :3], T_rel[:3, 3]
        Ri, ti = R.T, -R.T @ t
        for k, p in enumerate(pool):
            if p.moving_type == VERTEX:
                x, solid, f = R @ self.moving.vertices[p.moving_index] + t, self.fixed, \
                    p.fixed_index
            elif p.fixed_type == VERTEX:
                x, solid, f = Ri @ self.fixed.vertices[p.fixed_index] + ti, self.moving, \
                    p.moving_index
            else:
                continue
            d = distances[k]
            to_face = float(solid.face_distance(f, x[None])[0])
            if d >= 0:
                out[k] = to_face <= d + tol
            elif solid.contains(x[None])[0] > 0.5:
                out[k] = to_face <= float(solid.distance_to_surface(x[None])[0]) + tol
            else:
                out[k] = False
        return out

    def last_guard(self) -> np.ndarray:
        """Guard flags of the last frame's pool (see :meth:`_guarded`)."""
        return self._guard

    def _climb(self, h: Hypothesis) -> Hypothesis:
        keys = list(self._fc.groups)
        for _ in range(2 * len(keys) + 1):
            best = h
            for k in keys:
                s = h.state - {k} if k in h.state else h.state | {k}
                c = self.evaluate(s)
                if c is not None and c.score < best.score - 1e-9 and self.supported(c):
                    best = c
            if best is h:
                return h
            h = best
        return h

    def nested(self, h: Hypothesis) -> List[Hypothesis]:
        """
        Relations nested in ``h`` (its groups less one or more) with a lower rank, best first.

        Scored in the current frame: each group of ``h`` dropped in turn, and again from the
        best of those (two levels).
        """
        out: Dict[State, Hypothesis] = {}
        level = [h]
        for _ in range(2):
            nxt = []
            for g in level:
                for k in g.state:
                    s = g.state - {k}
                    if s in out:
                        continue
                    c = self.evaluate(s)
                    if c is not None:
                        out[s] = c
                        nxt.append(c)
            level = sorted(nxt, key=lambda c: c.score)[:2]
        return sorted((c for c in out.values() if c.rank < h.rank and self.supported(c)),
                      key=lambda c: c.score)

    def evidence_check(self, h: Hypothesis) -> Hypothesis:
        """
        Drop constraints of ``h`` that the current frame rejects (``evidence_chi2``).

        :returns: ``h``, or the best-scoring nested relation whose chi2 is lower than ``h``'s by
            more than ``evidence_chi2`` per constraint dropped.
        """
        if self.options.evidence_chi2 <= 0 or not h.state or not np.isfinite(h.chi2):
            return h
        for c in self.nested(h):
            if h.chi2 - c.chi2 > self.evidence_limit(h.rank - c.rank):
                return c
        return h

    def evidence_limit(self, dropped: int, innovation: bool = False) -> float:
        """
        Return the chi2 decrease that rejects ``dropped`` constraints.

        At ``evidence_chi2``'s level (``innovation``: ``innovation_evidence_chi2``'s).
        """
        levels = self._innovation if innovation else self._evidence
        return levels[min(max(int(dropped), 1), 6)]

    def evaluate(self, state: State) -> Optional[Hypothesis]:
        """
        Score the relation ``state`` in the current frame.

        Score of the relation ``state`` in the current frame (None if one of its groups is
        not in the pool: the relation is not possible within the margin).
        """
        fc = self._fc
        if state in fc.hypotheses:
            return fc.hypotheses[state]
        if any(k not in fc.groups for k in state):
            return None
        n = len(fc.pool)
        mask = np.zeros(n, dtype=bool)
        for k in state:
            mask[fc.groups[k]] = True
        # chi2 = d^T (A A^T + s2 I)^-1 d through the 6x6 normal matrix (Woodbury):
        # = (d.d - b^T (s2 I + A^T A)^-1 b) / s2, b = A^T d; correction = -(s2 I + A^T A)^-1 b
        s2 = self.options.sigma_model ** 2
        N = np.zeros((6, 6))
        b = np.zeros(6)
        dd = 0.0
        Nc = np.zeros((6, 6))
        for k in state:
            gN, gb, gdd, gNc = self._gsum[k]
            N += gN
            b += gb
            dd += gdd
            Nc += gNc
        if state:
            w = eigvalsh(Nc)
            rank = int(np.count_nonzero(w > 1e-4 * max(w[-1], 1e-300)))
        else:
            rank = 0
        active = mask.copy()
        pushed = 0
        A, d = self._A, self._d
        s2I = s2 * _EYE6
        lim = -3.0 * self.options.sigma_model
        for _ in range(4):
            if not active.any():
                chi2, delta = 0.0, np.zeros(6)
            else:
                y = solve(N + s2I, b)
                chi2 = float(max(dd - b @ y, 0.0) / s2)
                delta = -y
            r = d + A @ delta
            new = (~active) & self._guard & (r < lim)
            if not new.any():
                break
            idx = np.flatnonzero(new)
            active[idx] = True
            N = N + self._P[idx].sum(0)
            b = b + (A[idx] * d[idx, None]).sum(0)
            dd += float(d[idx] @ d[idx])
            pushed = int(np.count_nonzero(active & ~mask))
        h = Hypothesis(state, tuple(compress(fc.pool, mask.tolist())), chi2, rank,
                       chi2 + self.penalty * (6 - rank), pushed, delta)
        fc.hypotheses[state] = h
        return h


# --- temporal model --------------------------------------------------------------------------

def _transition(options: RecognitionOptions, a: State, b: State) -> float:
    """Cost of the change of contact state ``a`` -> ``b`` between consecutive frames."""
    n = len(a ^ b)
    return options.switch_cost * n + (options.transition_cost if n else 0.0)


class RelationTracker:
    """
    Online Viterbi over contact relations (hysteresis).

    Online Viterbi over contact relations (hysteresis): feed frames in order with
    :meth:`update`; :meth:`reset` after a gap in the track.

    :param recognizer: the per-frame scorer.
    """

    def __init__(self, recognizer: RelationRecognizer) -> None:
        self.recognizer = recognizer
        self.reset()

    def reset(self) -> None:
        """Forget the track (e.g. after a jump in time or a new object)."""
        self._cost: Dict[State, float] = {}
        self._prev: Dict[State, Hypothesis] = {}
        self.history: List[Tuple[FrameCandidates, Dict[State, Tuple[float, Optional[State]]],
                                 Dict[State, float]]] = []

    def frame_score(self, h: Hypothesis) -> float:
        """
        Cost of ``h`` in the current frame for the temporal model.

        ``h.score``; with ``noise_correlation`` rho > 0 and ``h``'s relation scored in the
        previous frame too, the correction's part of the chi2 is that of the innovation of the
        noise estimate (``|delta_k - rho delta_(k-1)|^2 / (1 - rho^2)``, the AR(1) likelihood).
        """
        rho = self.recognizer.options.noise_correlation
        if rho <= 0 or h.delta is None or not np.isfinite(h.score):
            return h.score
        p = self._prev.get(h.state)
        if p is None and self._prev:
            # a relation not scored in the previous frame: its noise estimate there
            p = self.recognizer.evaluate_previous(h.state)
        if p is None or p.delta is None:
            return h.score
        e = h.delta - rho * p.delta
        return float(h.score - h.delta @ h.delta + (e @ e) / (1.0 - rho * rho))

    def innovation_check(self, h: Hypothesis) -> Hypothesis:
        """
        Drop constraints of ``h`` that the change since the previous frame rejects (online).

        With ``noise_correlation`` rho > 0 and ``innovation_evidence_chi2`` > 0: the evidence
        rule of :meth:`RelationRecognizer.evidence_check`, at ``innovation_evidence_chi2``'s
        level, on the innovation chi2 (the correction part of :meth:`frame_score`,
        ``|delta_k - rho delta_(k-1)|^2 / (1 - rho^2)``) instead of the frame's chi2. A
        contact held after its release needs a correction that grows from one frame to the
        next (a peg lifted 3.3 mm per frame off a slot's floor: innovation chi2 22 held, 6.5
        released, where the frame's chi2 is 9.7 against 5.1); a nested relation whose
        innovation chi2 is lower by more than that level for the constraints it drops is used
        for this frame. The paths of the temporal model are unchanged (a relation held
        through an outlier frame is taken up again).

        :returns: ``h``, or the best-scoring nested relation the innovation test prefers.
        """
        rec = self.recognizer
        if rec.options.noise_correlation <= 0 or rec.options.innovation_evidence_chi2 <= 0 \
                or not h.state or not self._prev or h.delta is None:
            return h
        held = self.innovation_chi2(h)
        if held <= rec.evidence_limit(1, innovation=True):   # the smallest: none passes
            return h
        for c in rec.nested(h):
            if c.delta is not None and held - self.innovation_chi2(c) \
                    > rec.evidence_limit(h.rank - c.rank, innovation=True):
                return c
        return h

    def _onset_check(self, h: Hypothesis, fc: FrameCandidates) -> Hypothesis:
        """
        Take a contact up at its first frame when the frame pays for it (online).

        The mirror of the online safe rule: a relation with more constraints than the chosen
        one whose score (chi2 plus the free-DOF penalties) is lower by more than one free
        DOF's penalty, and whose forward cost is within ``ambiguity_margin`` of the chosen
        path's (only the transition into it keeps it behind), is used for this frame's
        output; the best-scoring such relation. The hysteresis alone would enter the new
        contact a frame or two late, the correction enforcing the old relation meanwhile:
        a peg leaving a hole's mouth onto the block's top face, still held against a wall of
        the hole, was pulled back (ADD 0.26 -> 0.85 mm, stated noise 0.5 mm). The paths of the
        temporal model are unchanged.

        :param h: the chosen relation (the end of the least-cost path).
        :param fc: this frame's candidates (the forward costs, :attr:`_cost`, are this
            frame's, relative to ``h``'s path).
        """
        rec = self.recognizer
        margin = rec.options.ambiguity_margin
        rivals = [fc.hypotheses[s] for s, c in self._cost.items()
                  if s != h.state and c <= margin and fc.hypotheses[s].rank > h.rank
                  and fc.hypotheses[s].score < h.score - rec.penalty]
        return min(rivals, key=lambda c: c.score) if rivals else h

    def _drop_boundary_groups(self, h: Hypothesis, fc: FrameCandidates) -> Hypothesis:
        """
        Return ``h`` less its face-face groups that share no area (online, the chosen relation).

        :meth:`RelationRecognizer.boundary_groups` at ``h``'s corrected pose; a wrong group
        moves that pose, so the others may fail there too (a T-peg in its slot taken against
        the block's front face: pulled out of the slot, the slot's walls share no area with
        its sides either). The relations less one failing group are scored, and the best one
        with every face-face group an area contact at its own corrected pose is used; else
        ``h`` less every failing group (the contacts common to them: a subset of ``h``).

        :param h: the chosen relation, a hypothesis of the current frame ``fc``.
        """
        rec = self.recognizer
        bad = rec.boundary_groups(h)
        if not bad:
            return h
        fine = [c for c in (rec.evaluate(h.state - {k}) for k in bad)
                if c is not None and c.delta is not None and not rec.boundary_groups(c)]
        if fine:
            return min(fine, key=lambda c: c.score)
        return rec.evaluate(h.state - bad) or fc.hypothesis(h.state - bad)

    def innovation_chi2(self, h: Hypothesis) -> float:
        """
        Return the chi2 of ``h`` in the current frame with its correction part the innovation's.

        :meth:`frame_score` less the free-DOF penalty (``h.chi2`` when the innovation is not
        available: ``noise_correlation`` 0 or the relation not possible in the frame before).
        """
        return self.frame_score(h) - h.score + h.chi2

    def update(self, T_moving: np.ndarray, T_fixed: np.ndarray,
               keep_history: bool = False, extra_states: Sequence[State] = ()
               ) -> Tuple[Hypothesis, FrameCandidates]:
        """
        Relation for the next frame: the end state of the least-cost path so far.

        :param keep_history: record the back-pointers for :meth:`backtrack` (offline use).
        :param extra_states: relations to score and keep as candidates of this frame besides
            the search's best (offline: the relations of the frames that follow).
        :returns: (chosen hypothesis, the frame's candidates).
        """
        rec = self.recognizer
        fc = rec.frame(T_moving, T_fixed, seeds=list(self._cost) + list(extra_states))
        # the beam: the best relations, at most one per (rank, correction size): relations
        # that differ only by groups adding nothing (e.g. either wall of a tight slot) would
        # otherwise fill it and hide the alternatives
        cand: List[Hypothesis] = []
        seen = set()
        for h in fc.ranked():
            sig = (h.rank, round(h.chi2, 1))
            if sig in seen or not rec.supported(h):
                continue
            seen.add(sig)
            cand.append(h)
            if len(cand) >= max(1, rec.options.beam):
                break
        for s in list(self._cost) + list(extra_states):   # previous (and given) states that
            h = fc.hypotheses.get(s) or rec.evaluate(s)       # are still possible: keep them
            if h is not None and h not in cand and rec.supported(h):
                cand.append(h)
        new: Dict[State, Tuple[float, Optional[State]]] = {}
        fscore: Dict[State, float] = {}
        for h in cand:
            if self._cost:
                prev, c = min(((p, c + _transition(rec.options, p, h.state))
                               for p, c in self._cost.items()), key=lambda x: x[1])
            else:
                prev, c = None, 0.0
            # offline only (see ``noise_correlation``): online, a wrong relation held from the
            # first frames with a steady offset costs 12 times less per frame at rho 0.85
            fscore[h.state] = self.frame_score(h) if keep_history else h.score
            new[h.state] = (c + fscore[h.state], prev)
        # keep a beam of the cheapest paths (costs relative to the best, to stay bounded)
        ordered = sorted(new.items(), key=lambda kv: kv[1][0])[:max(1, rec.options.beam) + 2]
        if keep_history:
            # offline, the relation explaining this frame best at each rank stays in the beam
            # whatever its path's cost: a contact change pays its transition cost at its first
            # frame, so there its path is dearer than those holding the old relation and was
            # pruned, and the back-tracking could only make the change a frame late (a T-peg
            # lifted 2.2 mm off its slot's floor held on it for a frame: 3.4 mm along the free
            # direction)
            best_of_rank: Dict[int, State] = {}
            for s in new:
                r = fc.hypotheses[s].rank
                if r not in best_of_rank or fscore[s] < fscore[best_of_rank[r]]:
                    best_of_rank[r] = s
            kept = {s for s, _ in ordered}
            ordered += [(s, new[s]) for s in best_of_rank.values() if s not in kept]
            ordered.sort(key=lambda kv: kv[1][0])
        base = ordered[0][1][0]
        self._cost = {s: c - base for s, (c, _) in ordered}
        if keep_history:
            self.history.append((fc, {s: (c - base, p) for s, (c, p) in ordered},
                                 {s: fscore[s] for s, _ in ordered}))
        best_state = ordered[0][0]
        h = fc.hypotheses[best_state]
        margin = rec.options.ambiguity_margin
        if margin > 0:
            # the online safe rule: the forward costs play the min-marginals' part (the
            # evidence of the frames to come is unknown); where a relation with fewer
            # constraints explains this frame better and its forward cost is within the margin,
            # only the groups common to both are enforced
            near = [s for s, _ in ordered[1:] if self._cost[s] <= margin
                    and fc.hypotheses[s].rank < h.rank
                    and fc.hypotheses[s].chi2 < h.chi2 - AMBIGUITY_FIT]
            common: State = frozenset()
            if near:
                states = [best_state] + near
                if not keep_history and rec.options.area_contact_check:
                    # each relation without its faces that meet only along a boundary (the
                    # area check, as below): the groups common to relations sharing such a face
                    # can be that face alone (a T-peg entering its slot, its back face level
                    # with the block's front face, was corrected against that face alone and
                    # pulled 2 mm out of the slot: contact_tracks --seed 7, ADD 2.0 -> 4.4 mm)
                    states = [st - rec.boundary_groups(fc.hypotheses[st]) for st in states]
                common = common_state(states)
            if common:
                # (not when nothing is common: the observation would be passed through or,
                # penetrating, pushed out, which may move it along the free directions)
                h = fc.hypothesis(common)
        if margin > 0 and not keep_history and h.state == best_state:
            h = self._onset_check(h, fc)
        if h.state in fc.hypotheses:
            h = rec.evidence_check(h)
            if not keep_history:
                h = self.innovation_check(h)
        if not keep_history and rec.options.area_contact_check and h.state in fc.hypotheses:
            h = self._drop_boundary_groups(h, fc)
        self._prev = fc.hypotheses     # the noise estimates of this frame, for the next one
        return h, fc

    def backtrack(self) -> List[Hypothesis]:
        """
        Find the least-cost relation sequence over the recorded frames (offline Viterbi).

        With ``ambiguity_margin`` > 0, each frame's min-marginals (the least total cost of a
        sequence through a relation at that frame: forward + backward cost) are computed; the
        groups common to the Viterbi relation and every relation whose min-marginal is within
        the margin of it are enforced (at a contact change whose frame the evidence does not
        pin down, only what holds before and after it).
        """
        if not self.history:
            return []
        opts = self.recognizer.options
        margin = opts.ambiguity_margin
        # backward costs over the recorded beams
        betas: List[Dict[State, float]] = [{} for _ in self.history]
        betas[-1] = {s: 0.0 for s in self.history[-1][1]}
        for k in range(len(self.history) - 2, -1, -1):
            _, table1, score1 = self.history[k + 1]
            nxt = [(s1, score1[s1] + betas[k + 1][s1]) for s1 in table1]
            betas[k] = {s: min(c + _transition(opts, s, s1) for s1, c in nxt)
                        for s in self.history[k][1]}
        out: List[Hypothesis] = []
        fc, table, _ = self.history[-1]
        state = min(table, key=lambda s: table[s][0])
        for k in range(len(self.history) - 1, -1, -1):
            fc, table, _ = self.history[k]
            if state not in table:    # pruned from this frame's beam: take its best
                state = min(table, key=lambda s: table[s][0] + betas[k][s])
            h = fc.hypotheses[state]
            if margin > 0:
                mu = {s: table[s][0] + betas[k][s] for s in table}
                near = [s for s in table if mu[s] <= mu[state] + margin
                        and fc.hypotheses[s].rank < h.rank
                        and fc.hypotheses[s].chi2 < h.chi2 - AMBIGUITY_FIT]
                if near:
                    h = fc.hypothesis(common_state([state] + near))
            out.append(h)
            state = table[state][1]
            if state is None:
                state = frozenset()
        return out[::-1]


def recognise_track(recognizer: RelationRecognizer, moving_poses: np.ndarray,
                    fixed_poses: np.ndarray, smooth: bool = True,
                    return_guards: bool = False) -> tuple:
    """
    Relations of a whole track: Viterbi back-tracking (``smooth``) or the online choice.

    With ``smooth`` and the options' ``lookahead`` > 0, two forward passes: the second one
    scores at each frame also the relations kept in the beams of the next ``lookahead``
    frames of the first, then back-tracks.

    :param moving_poses: observed poses (N, 4, 4); frames with non-finite poses get the empty
        relation and break the chain.
    :param fixed_poses: fixed poses (N, 4, 4).
    :returns: per frame the chosen hypothesis and the frame's candidates (and, with
        ``return_guards``, the pool's guard flags).
    """
    Tm = np.asarray(moving_poses, dtype=float).reshape(-1, 4, 4)
    Tf = np.asarray(fixed_poses, dtype=float).reshape(-1, 4, 4)
    chosen: List[Optional[Hypothesis]] = []
    frames: List[FrameCandidates] = []
    guards: List[np.ndarray] = []
    segment: List[int] = []
    tracker = RelationTracker(recognizer)
    empty = Hypothesis(frozenset(), (), 0.0, 0, float('nan'))

    def flush() -> None:
        if smooth and segment:
            for k, h in zip(segment, tracker.backtrack()):
                chosen[k] = h
        tracker.reset()
        segment.clear()

    beam_states: List[List[State]] = [[] for _ in range(len(Tm))]
    recognizer.area_check = bool(smooth and recognizer.options.area_contact_check)

    def forward(ahead: Optional[List[List[State]]]) -> None:
        for k in range(len(Tm)):
            if not (np.all(np.isfinite(Tm[k])) and np.all(np.isfinite(Tf[k]))):
                flush()
                chosen.append(empty)
                frames.append(FrameCandidates([], {}))
                guards.append(np.zeros(0, dtype=bool))
                continue
            h, fc = tracker.update(Tm[k], Tf[k], keep_history=smooth,
                                   extra_states=ahead[k] if ahead is not None else ())
            chosen.append(h)
            frames.append(fc)
            guards.append(recognizer.last_guard())
            beam_states[k] = list(tracker._cost)
            segment.append(k)
        flush()

    forward(None)
    lookahead = recognizer.options.lookahead
    if smooth and lookahead > 0:
        # offline, a second pass: each frame also scores the relations that the first pass
        # kept in the beams of the frames that follow (a contact formation entered with
        # little evidence, e.g. a T-peg 1.5 mm into its slot, is not among the search's
        # best at the first frames; without it as a candidate there the back-tracking can
        # only choose what the noise favoured)
        ahead = []
        for k in range(len(Tm)):
            seen: Dict[State, None] = {}
            for j in range(k + 1, min(len(Tm), k + 1 + lookahead)):
                for s in beam_states[j]:
                    seen.setdefault(s)
            ahead.append(list(seen))
        chosen.clear()
        frames.clear()
        guards.clear()
        forward(ahead)
    if return_guards:
        return chosen, frames, guards
    return chosen, frames
