"""
Naming identical parts whose known poses went stale (pure core, no ROS).

Two parts with the same shape (``link_base`` and ``link_arm``: the same brick) cannot be told
apart by geometry. Each tracker's global search (:meth:`ObjectTracker.update`) finds the places
that fit the shape and pass the quality check (``ObjectTracker.places``), and on its own names
one only within ``twin_reacquire_radius`` of its known pose (a hint or the pose before a loss).
When the known poses are stale (hints of frame 0 while a free-running camera is already at a
later frame: the parts moved 50-160 mm), every search ends ``ambiguous`` and no part gets a pose.

:func:`name_identical_parts` names the whole group at once: the verified places found in one
cloud by the group's searches are pooled, places that overlap are one physical part (a part
that fits in two overlapping ways is not named at all), and the parts are assigned to the
places by the minimum summed mean displacement from their known poses (the assignment
problem, solved exactly by enumeration: a group has 2-3 parts and a few places). The
assignment is *certain*
when its cost is less than half that of the best different assignment (the same rule as
``ObjectTracker._assign_among_twins``); otherwise the parts are still named, with
``ObjectTracker.naming_uncertain`` set: the node publishes the poses and flags them in the
status (a verified pose under an honest flag, rather than no pose at all).

Poses are 4x4 transforms model frame -> sensor frame [m].
"""

from __future__ import annotations

import itertools
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from object_localizer.tracking import mean_displacement, ObjectTracker, overlap, \
    symmetric_distance, TrackerSettings, TrackingModel, TrackUpdate

#: (pose 4x4 model -> sensor, age [s] or None for a hint of unknown age)
KnownPose = Tuple[np.ndarray, Optional[float]]

__all__ = ['name_identical_parts', 'identical_groups', 'may_name', 'known_radius']


def identical_groups(trackers: Dict[str, ObjectTracker]) -> List[List[str]]:
    """Return the groups (2 or more names, in ``trackers`` order) of parts with the same shape."""
    groups: List[List[str]] = []
    for name, tracker in trackers.items():
        if not tracker.twins or any(name in g for g in groups):
            continue
        twins = {id(t) for t in tracker.twins}
        groups.append([n for n, t in trackers.items() if n == name or id(t) in twins])
    return groups


def _frame_change(a: TrackingModel, b: TrackingModel) -> Optional[np.ndarray]:
    """
    Return X (4x4) with ``T_b @ X`` the pose of ``a`` at the place of ``b`` at ``T_b``.

    Identical parts may have different origins (``link_base`` and ``link_arm``: the same brick
    with its origin at different corners); the shift between their box centres is checked to
    make the surfaces coincide (mean nearest distance below 1 mm), else None.
    """
    from scipy.spatial import cKDTree

    X = np.eye(4)
    X[:3, 3] = b.centre - a.centre
    moved = a.probe + X[:3, 3]
    return X if float(np.mean(cKDTree(b.points).query(moved)[0])) < 0.001 else None


def _pooled_places(group: Sequence[ObjectTracker]) -> List[Tuple[np.ndarray, object]]:
    """
    Return the distinct places (pose, quality) found by the group's searches, best first.

    Poses are of ``group[0].model`` (places found by a twin with another origin are moved into
    that frame; a twin whose frame cannot be matched contributes nothing).
    """
    model = group[0].model
    found = []
    for t in group:
        X = np.eye(4) if t.model is model else _frame_change(model, t.model)
        if X is not None:
            found += [(pose @ X, q) for pose, q in t.places]
    places: List[Tuple[np.ndarray, object]] = []
    for pose, q in sorted(found, key=lambda pq: -pq[1].quality):
        if all(symmetric_distance(model, pose, p) > group[0].settings.ambiguity_distance
               for p, _ in places):
            places.append((pose, q))
    return places


def _clusters(model, places: list, depth: float) -> List[List[int]]:
    """Group the places whose volumes overlap (> 10 % deeper than ``depth`` [m]): one part."""
    parent = list(range(len(places)))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i
    for i, j in itertools.combinations(range(len(places)), 2):
        if overlap(model, places[i][0], model, places[j][0], depth) > 0.1:
            parent[root(j)] = root(i)
    groups: Dict[int, List[int]] = {}
    for i in range(len(places)):
        groups.setdefault(root(i), []).append(i)
    return list(groups.values())


def name_identical_parts(group: Sequence[ObjectTracker], stamp_ns: int,
                         accept_uncertain: bool = False) -> Dict[int, TrackUpdate]:
    """
    Name a group of identical parts, none verified in this cloud, from the places found.

    The distinct verified places of the group's searches are pooled and grouped by overlap
    (places whose volumes overlap are alternatives for one physical part). Only when every
    such cluster holds a single place (no part of the scene fits the shape in two distinct
    ways: two bricks end to end form a longer box along which a brick slides, and then nothing
    is named) and there are at least as many clusters as parts, the parts are assigned to
    clusters by the minimum summed mean displacement from their known poses.

    :param group: trackers of parts with the same shape; each searched this cloud (its
        ``places``) and has a known pose (``known_pose()``: hint or last verified pose).
    :param stamp_ns: the cloud's stamp [ns].
    :param accept_uncertain: name the parts also when the assignment is not decisive (flagged
        ``naming_uncertain``); False: then nothing is named.
    :return: ``{index in group: TrackUpdate}`` for the parts started at a place (state
        TRACKING, or STATIC for static parts); empty when nothing could be named. The trackers
        of the parts named are started (as by their own acquisition), and their
        ``naming_uncertain`` is set when the assignment was not decisive (its cost not below
        half the next one's).
    """
    known = [t.known_pose() for t in group]
    if len(group) < 2 or any(k is None for k in known):
        return {}
    places = _pooled_places(group)
    model, s = group[0].model, group[0].settings
    shifts = [np.eye(4) if t.model is model else _frame_change(model, t.model) for t in group]
    if any(X is None for X in shifts):
        return {}
    known = [k @ X for k, X in zip(known, shifts)]      # all in ``model``'s frame
    clusters = _clusters(model, places, s.max_penetration)
    if len(clusters) < len(group) or any(len(c) != 1 for c in clusters):
        return {}
    places = [places[c[0]] for c in clusters]
    cost = np.array([[mean_displacement(model, pose, k) for pose, _ in places] for k in known])
    options = sorted(
        (float(sum(cost[part, place] for part, place in enumerate(chosen))), chosen)
        for chosen in itertools.permutations(range(len(places)), len(group)))
    best_cost, best = options[0]
    next_cost = options[1][0] if len(options) > 1 else float('inf')
    certain = best_cost < 0.5 * next_cost
    if not certain and not accept_uncertain:
        return {}
    names = ', '.join(t.model.name for t in group)
    how = (f'named among the identical parts {names} by the assignment to {len(places)} '
           f'verified places nearest their known poses (summed {1e3 * best_cost:.0f} mm; next '
           f'{1e3 * next_cost:.0f} mm)'
           + ('' if certain else ': NAMING UNCERTAIN, the parts may be swapped'))
    out: Dict[int, TrackUpdate] = {}
    for part, place in enumerate(best):
        tracker = group[part]
        pose, q = places[place]
        if tracker.model is not model:     # into this part's own frame
            X = _frame_change(tracker.model, model)
            if X is None:
                continue
            pose = pose @ X
        out[part] = tracker._start(stamp_ns, pose, q, f'acquired ({1e3 * cost[part, place]:.0f} '
                                   f'mm from its known pose); {how}', acquired=True)
        tracker.naming_uncertain = tracker.naming_uncertain or not certain
    return out


def known_radius(age: Optional[float], settings: TrackerSettings) -> float:
    """
    Return how far [m, mean displacement] a part may have moved from a pose known ``age`` ago.

    ``twin_reacquire_radius + twin_max_speed x age`` (a hint, age None: the radius alone).
    """
    grown = 0.0 if age is None else settings.twin_max_speed * max(float(age), 0.0)
    return settings.twin_reacquire_radius + grown


def may_name(model: TrackingModel, pose: np.ndarray, own: Sequence[KnownPose],
             open_twins: Sequence[Tuple[TrackingModel, Sequence[KnownPose]]],
             settings: TrackerSettings) -> Tuple[bool, str]:
    """
    Decide whether a verified place ``pose`` of ``model`` may carry this part's name.

    Identical parts cannot be told apart by geometry: only where each was last seen (and where
    its motion would have taken it) names a place. Distances are mean displacements of the
    model's points, each divided by the radius the part may have moved since that pose was
    verified (:func:`known_radius`; older knowledge says less). The place is this part's when
    its nearest own expected pose (last verified pose or prediction) is within that radius
    (normalised distance <= 1) and less than half the normalised distance of every twin not
    verified in this cloud (a twin verified in this cloud already took its place: the
    penetration check keeps this part out of it). Otherwise nothing is named: a swapped name
    is worse than no pose.

    :param own: this part's expected poses with their ages (``ObjectTracker.expected_poses``).
    :param open_twins: (model, expected poses) of every identical part not verified in this
        cloud; a twin whose origin differs is compared at the same place (box centres shifted).
    :return: (may name, why not).
    """
    if not own:
        return False, 'no known pose of this part'
    own_d = [(mean_displacement(model, pose, T), known_radius(a, settings)) for T, a in own]
    d_own, r_own = min(own_d, key=lambda dr: dr[0] / dr[1])
    if d_own > r_own:
        return False, (f'{1e3 * d_own:.0f} mm from its known pose or prediction, beyond the '
                       f'{1e3 * r_own:.0f} mm it may have moved')
    for twin, expected in open_twins:
        X = np.eye(4) if twin is model else _frame_change(model, twin)
        if X is None:
            return False, f'{twin.name} has the same shape in an unmatched frame'
        if not expected:
            continue       # a twin with no known pose: it names nothing
        d_twin = min(mean_displacement(model, pose, T @ X) / known_radius(a, settings)
                     for T, a in expected)
        if not d_own / r_own < 0.5 * d_twin:
            return False, (f'not clearly nearer its own known pose than that of {twin.name} '
                           f'({d_own / r_own:.2f} vs {d_twin:.2f} of their radii)')
    return True, ''
