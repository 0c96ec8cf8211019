"""The per-frame fast paths (compiled kernels, batched queries) equal their reference forms."""

from contact_correction import contact_relation as cr
from contact_correction.contact_relation import (
    ContactPair, detect_contact_relation, EDGE, penetration_depth, relative_pose)
from contact_correction.nonlinear_correction import correct_nonlinear
from contact_correction.small_linalg import eigvalsh, solve, svd
from contact_correction.tracks import make_tracks, noisy_track, track_models
import numpy as np
import pytest
from stereo_manip_tools.transforms import rotation_log


@pytest.fixture(scope='module')
def observed():
    """Noisy observations (fixed-frame relative poses) on every benchmark track."""
    rng = np.random.default_rng(7)
    out = []
    for tr in make_tracks(track_models()):
        Tf, _, To = noisy_track(tr, rng, 1.5e-3, np.deg2rad(2.0))
        for k in rng.choice(len(To), 6, replace=False):
            out.append((tr.moving, tr.fixed, relative_pose(To[k], Tf)))
    return out


def test_nonlinear_compiled_equals_python_loop(observed):
    """Same iterate, residual and iteration count near noisy poses (also about a pivot)."""
    tried = 0
    for m, f, T in observed:
        pairs = detect_contact_relation(m, f, T, np.eye(4), tolerance=3e-3,
                                        penetration_tolerance=3e-3)
        if not pairs:
            continue
        for kw in ({}, {'length_scale': m.size / 16.0,
                        'anchor_schedule': (1e-1, 3e-2, 3e-3, 3e-4)},
                   {'pivot': m.centroid, 'length_scale': 1.5e-3 / np.deg2rad(2.0)}):
            ref = correct_nonlinear(m, f, T, pairs, compiled=False, **kw)
            fast = correct_nonlinear(m, f, T, pairs, compiled=True, **kw)
            assert fast.converged == ref.converged
            assert fast.max_residual == pytest.approx(ref.max_residual, abs=1e-13)
            if not ref.converged:
                # an unsatisfiable relation: the residual plateaus and which of the equal
                # iterates is kept depends on rounding; the caller uses the residual only
                continue
            assert fast.iterations == ref.iterations
            # rounding differs (BLAS vs loops), so iterates drift by ~1e-12 along directions a
            # rank-deficient relation leaves free; far below the 1e-9 m / rad identity bound
            assert np.abs(fast.T_rel[:3, 3] - ref.T_rel[:3, 3]).max() < 1e-10
            assert np.linalg.norm(rotation_log(fast.T_rel[:3, :3] @ ref.T_rel[:3, :3].T)) \
                < 1e-9
            tried += 1
    assert tried >= 20


def test_nonlinear_compiled_reports_parallel_edges_like_python_loop(observed):
    """An edge-edge pair with parallel edges raises the same ValueError on both paths."""
    m, f, _ = observed[0]
    T = np.eye(4)
    dm, df = m.edge_directions, f.edge_directions
    i, j = next((i, j) for i in range(len(dm)) for j in range(len(df))
                if np.linalg.norm(np.cross(dm[i], df[j])) < 1e-12)
    pairs = [ContactPair(EDGE, int(i), EDGE, int(j))]
    msgs = []
    for compiled in (False, True):
        with pytest.raises(ValueError, match='parallel edges') as exc:
            correct_nonlinear(m, f, T, pairs, compiled=compiled)
        msgs.append(str(exc.value))
    assert msgs[0] == msgs[1]


def test_faces_distance_equals_face_distance():
    """One call for many (face, point) pairs gives face_distance's values exactly."""
    rng = np.random.default_rng(3)
    for poly in track_models().values():
        faces = rng.integers(0, poly.n_faces, 300)
        pts = poly.bbox_min + rng.random((300, 3)) * (poly.bbox_max - poly.bbox_min) * 1.2
        ref = np.array([poly.face_distance(int(f), p[None])[0] for f, p in zip(faces, pts)])
        assert np.array_equal(poly.faces_distance(faces, pts), ref)


def test_penetration_of_equals_point_queries(observed):
    """The compiled depth equals in_bbox + contains + distance_to_surface on the same points."""
    positive = 0
    for m, f, T in observed:
        for dz in (0.0, -0.002, -0.006):
            T2 = T.copy()
            T2[2, 3] += dz
            pts = m.edge_samples(0.005) @ T2[:3, :3].T + T2[:3, 3]
            box = pts[f.in_bbox(pts)]
            inside = f.contains(box) > 0.5 + 1e-6 if len(box) else np.zeros(0, dtype=bool)
            ref = float(f.distance_to_surface(box[inside]).max()) if inside.any() else 0.0
            got = f.penetration_of(pts, 0.5 + 1e-6)
            assert got == ref
            positive += got > 1e-4
            assert penetration_depth(m, f, T2, np.eye(4)) >= got
    assert positive >= 5      # the comparison covers penetrating poses


def test_vertex_min_compiled_close_to_numpy(observed):
    """Within 1e-12 of the numpy form (the pool test decides within 1e-9 exactly)."""
    rng = np.random.default_rng(5)
    kernel = cr._vertex_min_kernel
    assert kernel is not None
    for m, _, T in observed[:8]:
        vs = rng.choice(m.feature_vertices, 40)
        n = rng.normal(size=(40, 3))
        n /= np.linalg.norm(n, axis=1)[:, None]
        for table in (m.vertex_edge_table(), m.vertex_face_table()):
            fast = cr._vertex_min(table, vs, T[:3, :3], n)
            try:
                cr._vertex_min_kernel = None
                ref = cr._vertex_min(table, vs, T[:3, :3], n)
            finally:
                cr._vertex_min_kernel = kernel
            assert np.abs(fast - ref).max() < 1e-12


def test_small_linalg_equals_numpy():
    """Bit-identical to np.linalg; a non-finite input raises LinAlgError as np.linalg does."""
    rng = np.random.default_rng(11)
    for shape in ((6, 6), (12, 6), (4, 3), (2, 3), (9, 3)):
        a = rng.normal(size=shape)
        for full in (True, False):
            for x, y in zip(svd(a, full_matrices=full), np.linalg.svd(a, full_matrices=full)):
                assert np.array_equal(x, y)
        assert np.array_equal(svd(a, compute_uv=False), np.linalg.svd(a, compute_uv=False))
    a = rng.normal(size=(10, 6))
    N = a.T @ a
    b = rng.normal(size=6)
    assert np.array_equal(eigvalsh(N), np.linalg.eigvalsh(N))
    assert np.array_equal(solve(N + np.eye(6), b), np.linalg.solve(N + np.eye(6), b))
    bad = np.full((3, 3), np.nan)
    with np.errstate(invalid='ignore'):
        with pytest.raises(np.linalg.LinAlgError):
            svd(bad)
        with pytest.raises(np.linalg.LinAlgError):
            solve(np.zeros((3, 3)), np.ones(3))
