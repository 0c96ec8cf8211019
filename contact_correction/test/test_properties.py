"""
Property tests.

For any small pose noise the optimal correction meets every contact, does not penetrate, and leaves
the free translation and the free rotation exactly as observed.
"""

from contact_correction.contact_relation import detect_contact_relation, penetration_depth
from contact_correction.correction import correct_pose
from contact_correction.optimal_correction import constraint_directions, constraint_matrix
from contact_correction.trajectory import correct_trajectory, trajectory_components
from hypothesis import example, given, settings, strategies as st
import numpy as np
from stereo_manip_tools.transforms import make_transform, rotation_about_axis, rotation_log

I4 = np.eye(4)
vec = st.tuples(*[st.floats(-1.0, 1.0)] * 3)
NAMES = ['cube_on_table', 'edge_on_face', 'vertex_on_face', 'peg_in_hole', 'peg_in_slot',
         'face_on_edge']


@settings(max_examples=30, deadline=None)
@given(name=st.sampled_from(NAMES), w=vec, dt=vec)
# a rotation of 5e-153 rad: the non-linear step's axis normalisation underflowed to 0 / 0
@example(name='cube_on_table', w=(0.0, 1.5274681817498023e-151, 0.0), dt=(0.0, 0.0, 0.0))
def test_optimal_invariants(configs, name, w, dt):
    m, f, T, rank = configs[name]
    w = np.deg2rad(2.0) * np.asarray(w)
    ang = float(np.linalg.norm(w))
    R = rotation_about_axis(w, ang) if ang > 0 else np.eye(3)
    T_obs = make_transform(R @ T[:3, :3], T[:3, 3] + 3e-3 * np.asarray(dt))
    pairs = detect_contact_relation(m, f, T, I4, 1e-7)
    r = correct_pose(m, f, T_obs, I4, pairs, check_penetration=False)
    assert r.corrected, r.status
    assert r.rotation_rank == rank
    assert r.max_residual < 1e-9
    assert penetration_depth(m, f, r.T_moving, I4, spacing=0.004) < 1e-9
    d = constraint_directions(constraint_matrix(m, f, r.T_moving, pairs)[0], m.size)
    assert np.abs(d.free_translation @ (r.T_moving[:3, 3] - T_obs[:3, 3])).max(
        initial=0.0) < 1e-12
    dr = rotation_log(r.T_moving[:3, :3] @ T_obs[:3, :3].T)
    assert np.abs(d.free_rotation @ dr).max(initial=0.0) < 1e-9


def test_trajectory_components_split_free_and_constrained(configs):
    m, f, T, _ = configs['peg_in_hole']
    rng = np.random.default_rng(11)
    obs = np.array([make_transform(T[:3, :3], T[:3, 3] + rng.normal(size=3) * 1e-3)
                    for _ in range(5)])
    res = correct_trajectory(m, f, obs, I4)
    comp = trajectory_components(res, obs, I4)
    assert list(comp['labels']) == ['constrained', 'constrained', 'free']
    assert np.allclose(comp['corrected'][:, 2], comp['observed'][:, 2], atol=1e-15)
    assert np.allclose(comp['corrected'][:, :2], 0.0, atol=1e-9)
