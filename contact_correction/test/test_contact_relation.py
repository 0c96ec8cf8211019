"""Contact relation detection, penetration depth and the Eq. 2 / Eq. 3 constraint ranks."""

from contact_correction.contact_relation import (
    detect_contact_relation, EDGE, evaluate_contacts, FACE, penetration_depth, VERTEX)
from contact_correction.optimal_correction import (
    constraint_directions, constraint_matrix, rotational_constraint_rank)
import numpy as np
import pytest
from stereo_manip_tools.transforms import make_transform

I4 = np.eye(4)


def kinds(pairs):
    return sorted(p.kind for p in pairs)


def test_relations_of_the_configurations(configs):
    expected = {
        'cube_on_table': ['vertex-face'] * 4,
        'edge_on_face': ['vertex-face'] * 2,
        'vertex_on_face': ['vertex-face'],
        # 4 bottom corners on 2 walls each, 4 rim corners on 2 peg faces each
        'peg_in_hole': ['face-vertex'] * 8 + ['vertex-face'] * 8,
        # 4 bottom corners: floor + wall; the slot's top edges cross the peg's vertical edges
        'peg_in_slot': ['edge-edge'] * 4 + ['vertex-face'] * 8,
        'face_on_edge': ['edge-edge'] * 2,
    }
    for name, (m, f, T, _) in configs.items():
        pairs = detect_contact_relation(m, f, T, I4, tolerance=1e-6)
        assert kinds(pairs) == sorted(expected[name]), name
        g = evaluate_contacts(m, f, T, pairs)
        assert np.abs(g.distances).max() < 1e-12, name
        assert np.allclose(np.linalg.norm(g.normals, axis=1), 1.0)


def test_relation_is_frame_independent(configs):
    m, f, T, _ = configs['peg_in_hole']
    W = make_transform(np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]]), [0.3, -0.2, 1.0])
    a = detect_contact_relation(m, f, T, I4, 1e-6)
    b = detect_contact_relation(m, f, W @ T, W, 1e-6)
    assert a == b


def test_tolerance_and_separation(configs):
    m, f, T, _ = configs['cube_on_table']
    up = T.copy()
    up[2, 3] += 1e-3
    assert detect_contact_relation(m, f, up, I4, tolerance=5e-4) == []
    pairs = detect_contact_relation(m, f, up, I4, tolerance=2e-3)
    assert len(pairs) == 4
    assert np.allclose(evaluate_contacts(m, f, up, pairs).distances, 1e-3)


def test_penetration_depth(configs):
    m, f, T, _ = configs['cube_on_table']
    assert penetration_depth(m, f, T, I4) < 1e-12
    down = T.copy()
    down[2, 3] -= 3e-3
    assert penetration_depth(m, f, down, I4) == pytest.approx(3e-3, abs=1e-9)
    # signed distances of the relation report it as negative
    pairs = detect_contact_relation(m, f, down, I4, tolerance=1e-3, penetration_tolerance=5e-3)
    assert len(pairs) == 4
    assert np.allclose(evaluate_contacts(m, f, down, pairs).distances, -3e-3)
    # peg pushed 2 mm sideways into the hole wall
    m, f, T, _ = configs['peg_in_hole']
    side = T.copy()
    side[0, 3] += 2e-3
    assert penetration_depth(m, f, side, I4, spacing=0.002) == pytest.approx(2e-3, abs=1e-9)


def test_eq2_rows_match_finite_differences(configs):
    """Each Eq. 2 row is the derivative of the contact distance along a screw."""
    from contact_correction.nonlinear_correction import apply_screw
    rng = np.random.default_rng(3)
    for name, (m, f, T, _) in configs.items():
        pairs = detect_contact_relation(m, f, T, I4, 1e-6)
        A, g = constraint_matrix(m, f, T, pairs)
        for _ in range(3):
            s = rng.normal(size=6)
            h = 1e-7
            d1 = evaluate_contacts(m, f, apply_screw(T, h * s[:3], h * s[3:]), pairs).distances
            d0 = evaluate_contacts(m, f, apply_screw(T, -h * s[:3], -h * s[3:]), pairs).distances
            assert np.allclose((d1 - d0) / (2 * h), A @ s, atol=1e-6), name


def test_rank_cases(configs):
    for name, (m, f, T, rank) in configs.items():
        pairs = detect_contact_relation(m, f, T, I4, 1e-6)
        A, _ = constraint_matrix(m, f, T, pairs)
        assert rotational_constraint_rank(A, m.size) == rank, name
        d = constraint_directions(A, m.size)
        assert len(d.constrained_rotation) + len(d.free_rotation) == 3
        assert len(d.constrained_translation) + len(d.free_translation) == 3


def test_constraint_directions_analytic(configs):
    # cube on a table: free rotation about the normal, free translation in the plane
    m, f, T, _ = configs['cube_on_table']
    d = constraint_directions(constraint_matrix(m, f, T,
                                                detect_contact_relation(m, f, T, I4))[0], m.size)
    assert abs(d.free_rotation[0] @ [0, 0, 1]) == pytest.approx(1.0)
    assert abs(d.constrained_translation[0] @ [0, 0, 1]) == pytest.approx(1.0)
    assert d.constraint_rank == 3
    # edge (along x) on the table: constrained rotation axis = n x l = y
    m, f, T, _ = configs['edge_on_face']
    d = constraint_directions(constraint_matrix(m, f, T,
                                                detect_contact_relation(m, f, T, I4))[0], m.size)
    assert abs(d.constrained_rotation[0] @ [0, 1, 0]) == pytest.approx(1.0)
    # peg in hole: everything constrained except sliding along the hole axis
    m, f, T, _ = configs['peg_in_hole']
    d = constraint_directions(constraint_matrix(m, f, T,
                                                detect_contact_relation(m, f, T, I4))[0], m.size)
    assert d.free_translation.shape == (1, 3)
    assert abs(d.free_translation[0] @ [0, 0, 1]) == pytest.approx(1.0)
    assert d.constraint_rank == 5


def test_element_types_of_pairs(configs):
    m, f, T, _ = configs['face_on_edge']
    pairs = detect_contact_relation(m, f, T, I4, 1e-6)
    assert all(p.moving_type == EDGE and p.fixed_type == EDGE for p in pairs)
    m, f, T, _ = configs['peg_in_hole']
    pairs = detect_contact_relation(m, f, T, I4, 1e-6)
    assert {(p.moving_type, p.fixed_type) for p in pairs} == {(VERTEX, FACE), (FACE, VERTEX)}
