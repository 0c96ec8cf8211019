"""Pure-core tests of the four-step stereo pipeline on small synthetic cases with known answers."""

from hypothesis import given, settings, strategies as st
import numpy as np
import pytest
from stereo_depth.aggregation import box_aggregate, box_sum_u16
from stereo_depth.evaluation import evaluate_disparity, nonoccluded_mask
from stereo_depth.matching_cost import (absolute_difference_cost, census_cost, census_planes,
                                        census_transform, quantize_cost, zncc_cost)
from stereo_depth.optimization import (belief_propagation, census_block_matching,
                                       semi_global_matching, sgm_disparities, stereo_energy,
                                       winner_take_all, winner_take_all_both)
from stereo_depth.pipeline import (available_methods, cloud_message_data, cloud_points,
                                   compute_disparity,
                                   disparity_to_depth,
                                   disparity_to_points)
from stereo_depth.refinement import (fill_invalid, left_right_check, median_filter,
                                     remove_speckles, right_disparity_from_cost, subpixel_refine)


def layered_pair(h=48, w=96, d_back=4, d_front=12, front=(30, 60), seed=0, noise=0.0):
    """
    Random-texture pair.

    Background at ``d_back``, a foreground band of left columns ``front`` at ``d_front``. Returns
    (left, right, truth, occluded) with the exact occluded band ``[front[0] - (d_front - d_back),
    front[0])`` of the left view.
    """
    rng = np.random.default_rng(seed)
    back = rng.uniform(0, 255, (h, w + d_front + 1))
    fore = rng.uniform(0, 255, (h, w + d_front + 1))
    a, b = front
    x = np.arange(w)
    is_front = (x >= a) & (x < b)
    left = np.where(is_front[None, :], fore[:, x], back[:, x])
    xr = np.arange(w)
    right_front = (xr + d_front >= a) & (xr + d_front < b)
    right = np.where(right_front[None, :], fore[:, np.clip(xr + d_front, 0, w + d_front)],
                     back[:, xr + d_back])
    truth = np.where(is_front, float(d_front), float(d_back))[None, :].repeat(h, axis=0)
    occluded = np.zeros((h, w), bool)
    occluded[:, a - (d_front - d_back):a] = True
    if noise > 0:
        left = left + rng.normal(0, noise, left.shape)
        right = right + rng.normal(0, noise, right.shape)
    return (left.astype(np.float32), right.astype(np.float32), truth.astype(np.float32),
            occluded)


def shifted_pair(h=40, w=80, shift=7, seed=1):
    """Right image = left texture moved ``shift`` pixels to the left (a fronto-parallel plane)."""
    rng = np.random.default_rng(seed)
    tex = rng.uniform(0, 255, (h, w + shift)).astype(np.float32)
    left = tex[:, :w]
    right = tex[:, shift:]
    return np.ascontiguousarray(left), np.ascontiguousarray(right)


# --- step 1: matching cost ------------------------------------------------------------------

def test_census_transform_matches_brute_force():
    rng = np.random.default_rng(2)
    img = rng.integers(0, 256, (9, 11)).astype(np.float32)
    codes = census_transform(img, (5, 3))
    pad = np.pad(img, ((1, 1), (2, 2)), mode='edge')
    for y in range(9):
        for x in range(11):
            bits = [int(pad[y + dy, x + dx] < img[y, x]) for dy in range(3) for dx in range(5)
                    if (dy, dx) != (1, 2)]
            assert int(codes[y, x]) == int(''.join(map(str, bits)), 2)


@pytest.mark.parametrize('window', [(5, 5), (3, 3), (5, 3), (7, 7), (9, 7), (1, 1)])
@pytest.mark.parametrize('kind', ['uint8', 'float', 'rgb'])
def test_census_planes_are_the_bytes_of_the_census_codes(window, kind):
    rng = np.random.default_rng(5)
    img = {'uint8': rng.integers(0, 256, (13, 17)).astype(np.uint8),
           'float': rng.uniform(0, 255, (13, 17)),
           'rgb': rng.integers(0, 256, (13, 17, 3)).astype(np.uint8)}[kind]
    codes = census_transform(img, window)
    planes = census_planes(img, window)
    nbits = window[0] * window[1] - 1
    assert planes.shape == (max(1, (nbits + 7) // 8), 13, 17) and planes.dtype == np.uint8
    for p in range(planes.shape[0]):
        np.testing.assert_array_equal(planes[p], (codes >> np.uint64(8 * p)) & np.uint64(255))


def test_census_cost_is_hamming_distance():
    left, right = shifted_pair(16, 24, 3)
    cost = census_cost(left, right, 8, (5, 5))
    cl, cr = census_transform(left, (5, 5)), census_transform(right, (5, 5))
    y, x, d = 7, 15, 5
    assert cost[y, x, d] == bin(int(cl[y, x]) ^ int(cr[y, x - d])).count('1')
    assert cost.dtype == np.uint8 and cost.shape == (16, 24, 8)
    # candidates outside the right image get the largest cost (24 bits for a 5x5 window)
    assert np.all(cost[:, 2, 3:] == 24)


@pytest.mark.parametrize('cost_name', ['ad', 'bt', 'census', 'zncc'])
def test_shifted_texture_recovered_exactly_by_each_cost(cost_name):
    shift = 7
    left, right = shifted_pair(shift=shift)
    if cost_name == 'ad':
        cost = box_aggregate(absolute_difference_cost(left, right, 16), (5, 5), False)
    elif cost_name == 'bt':
        cost = box_aggregate(absolute_difference_cost(left, right, 16, birchfield_tomasi=True),
                             (5, 5), False)
    elif cost_name == 'census':
        cost = box_sum_u16(census_cost(left, right, 16, (5, 5)), (5, 5))
    else:
        cost = zncc_cost(left, right, 16, (5, 5))
    disp = winner_take_all(cost)
    interior = disp[3:-3, shift + 3:-3]
    assert np.all(interior == shift), np.unique(interior, return_counts=True)


def test_zncc_is_invariant_to_gain_and_offset():
    left, right = shifted_pair(shift=5)
    c1 = zncc_cost(left, right, 12, (7, 7))
    c2 = zncc_cost(left, 0.5 * right + 30.0, 12, (7, 7))
    np.testing.assert_allclose(c1[:, 20:], c2[:, 20:], atol=1e-4)
    assert np.all(winner_take_all(c2)[4:-4, 12:-4] == 5)
    q = quantize_cost(c1, 30.0)
    assert q.dtype == np.uint8 and q.max() <= 60


def test_cost_rejects_bad_input():
    with pytest.raises(ValueError, match='differ in shape'):
        census_cost(np.zeros((10, 20)), np.zeros((10, 21)), 8)
    with pytest.raises(ValueError, match='max_disparity'):
        census_cost(np.zeros((10, 20)), np.zeros((10, 20)), 0)
    with pytest.raises(ValueError, match='bits'):
        census_transform(np.zeros((10, 20)), (9, 9))


# --- step 2: aggregation --------------------------------------------------------------------

def test_box_sum_matches_opencv_and_brute_force():
    rng = np.random.default_rng(3)
    cost = rng.integers(0, 63, (13, 17, 5)).astype(np.uint8)
    fast = box_sum_u16(cost, (5, 3))
    pad = np.pad(cost.astype(np.int64), ((1, 1), (2, 2), (0, 0)), mode='edge')
    ref = sum(pad[dy:dy + 13, dx:dx + 17] for dy in range(3) for dx in range(5))
    np.testing.assert_array_equal(fast, ref)
    mean = box_aggregate(cost.astype(np.float32), (5, 3))
    assert mean.shape == cost.shape
    np.testing.assert_allclose(mean[3:-3, 3:-3], ref[3:-3, 3:-3] / 15.0, rtol=1e-5)


# --- step 3: optimisation -------------------------------------------------------------------

def _sgm_reference(cost, p1, p2, directions, image=None, gamma=0.0):
    """
    Plain-python SGM path sums (Hirschmueller 2008, Eq. 13).

    With ``gamma`` > 0 the large-jump penalty of the step q -> p is max(P1, P2 gamma / (gamma +
    |I(p) - I(q)|)), rounded (Sec. 3.1).
    """
    h, w, nd = cost.shape
    c = cost.astype(np.int64)
    total = np.zeros_like(c)
    for dy, dx in directions:
        L = np.zeros_like(c)
        ys = range(h) if dy >= 0 else range(h - 1, -1, -1)
        xs = list(range(w)) if dx >= 0 else list(range(w - 1, -1, -1))
        for y in ys:
            for x in xs:
                py, px = y - dy, x - dx
                if 0 <= py < h and 0 <= px < w and (dy, dx) != (0, 0):
                    prev = L[py, px]
                    m = prev.min()
                    big = p2
                    if gamma > 0:
                        di = abs(float(image[y, x]) - float(image[py, px]))
                        big = int(np.rint(max(p1, p2 * gamma / (gamma + di))))
                    for d in range(nd):
                        cand = [prev[d], m + big]
                        if d > 0:
                            cand.append(prev[d - 1] + p1)
                        if d < nd - 1:
                            cand.append(prev[d + 1] + p1)
                        L[y, x, d] = c[y, x, d] + min(cand) - m
                else:
                    L[y, x] = c[y, x]
        total += L
    return total


@pytest.mark.parametrize('paths', [4, 8])
def test_sgm_equals_reference_recursion(paths):
    rng = np.random.default_rng(4)
    cost = rng.integers(0, 40, (7, 9, 6)).astype(np.uint8)
    dirs4 = [(0, 1), (0, -1), (1, 0), (-1, 0)]
    dirs8 = dirs4 + [(1, 1), (1, -1), (-1, 1), (-1, -1)]
    ref = _sgm_reference(cost, 3, 20, dirs8 if paths == 8 else dirs4)
    np.testing.assert_array_equal(semi_global_matching(cost, 3, 20, paths), ref)


@pytest.mark.parametrize('paths', [4, 8])
def test_intensity_adaptive_p2_equals_reference_recursion(paths):
    rng = np.random.default_rng(5)
    cost = rng.integers(0, 40, (7, 9, 6)).astype(np.uint8)
    image = rng.integers(0, 256, (7, 9)).astype(np.float32)
    dirs4 = [(0, 1), (0, -1), (1, 0), (-1, 0)]
    dirs8 = dirs4 + [(1, 1), (1, -1), (-1, 1), (-1, -1)]
    ref = _sgm_reference(cost, 3, 20, dirs8 if paths == 8 else dirs4, image, 30.0)
    got = semi_global_matching(cost, 3, 20, paths, image=image, gamma=30.0)
    np.testing.assert_array_equal(got, ref)
    assert not np.array_equal(got, semi_global_matching(cost, 3, 20, paths))


def test_directional_fill_takes_the_background_rank():
    d = np.full((9, 9), 10.0, np.float32)
    d[:, 5:] = 30.0                      # a near surface on the right
    d[3:6, 3:6] = np.nan                 # a hole touching both
    filled = fill_invalid(d, mode='directional', rank=0)
    assert np.all(np.isfinite(filled))
    assert np.all(filled[3:6, 3:6] == 10.0)    # rank 0: the farther (smaller) disparity
    ranked = fill_invalid(d, mode='directional', rank=7)
    assert ranked[4, 4] == 30.0                # highest rank: the near one is among the 8
    np.testing.assert_array_equal(filled[np.isfinite(d)], d[np.isfinite(d)])
    with pytest.raises(ValueError, match='rank'):
        fill_invalid(d, mode='directional', rank=-1)


def test_sgm_fronto_parallel_plane_gives_constant_disparity():
    left, right = shifted_pair(48, 96, 9)
    dl, dr = sgm_disparities(census_cost(left, right, 24, (7, 5)), 7, 100, 8)
    # integer disparity exact everywhere; the parabola's subpixel offsets scatter around it
    np.testing.assert_array_equal(np.rint(dl[:, 12:]), 9.0)
    assert abs(dl[:, 12:].mean() - 9.0) < 0.05
    np.testing.assert_array_equal(dr[:, 4:-12], 9.0)   # census border effects at x < 4


def test_wta_both_views_match_separate_computation():
    left, right, _, _ = layered_pair()
    cost = census_cost(left, right, 20, (5, 5))
    dl, dr = winner_take_all_both(cost)
    assert np.all(np.abs(dl - winner_take_all(cost)) <= 0.5)
    np.testing.assert_array_equal(dr, right_disparity_from_cost(cost))
    fl, fr = census_block_matching(left, right, 20, (5, 5), (3, 3))
    sl, sr = winner_take_all_both(box_sum_u16(cost, (3, 3)))
    np.testing.assert_array_equal(fl, sl)
    np.testing.assert_array_equal(fr, sr)


def _bp_case(seed=0, h=40, w=60, nd=16, noise=20.0):
    rng = np.random.default_rng(seed)
    truth = np.full((h, w), 3)
    truth[10:30, 20:45] = 9
    tex = rng.uniform(0, 255, (h, w + 20))
    left = np.array([[tex[y, x - truth[y, x] + 10] for x in range(w)] for y in range(h)])
    left = left + rng.normal(0, noise, (h, w))
    right = tex[:, 10:10 + w]
    cost = np.minimum(absolute_difference_cost(left, right, nd).astype(np.float32), 40) * 0.1
    return cost, truth


def test_bp_lowers_eq1_energy_monotonically():
    cost, truth = _bp_case()
    energies = []
    belief_propagation(cost, 1.0, 2.0, iterations=8, levels=1,
                       callback=lambda lev, it, lab: energies.append(
                           stereo_energy(cost, lab, 1.0, 2.0)))
    assert len(energies) == 8
    assert all(b <= a for a, b in zip(energies, energies[1:])), energies
    e_wta = stereo_energy(cost, winner_take_all(cost), 1.0, 2.0)
    e_true = stereo_energy(cost, truth, 1.0, 2.0)
    assert energies[-1] < 0.55 * e_wta
    assert energies[-1] < 1.06 * e_true


def test_hierarchical_bp_beats_flat_bp_and_keeps_best_labelling():
    cost, truth = _bp_case(seed=1)
    seen = []
    lab = belief_propagation(cost, 1.0, 2.0, iterations=5, levels=3,
                             callback=lambda lev, it, lab: seen.append(lab) if lev == 0 else None)
    e = stereo_energy(cost, lab, 1.0, 2.0)
    assert e == min(stereo_energy(cost, s, 1.0, 2.0) for s in seen)
    flat = belief_propagation(cost, 1.0, 2.0, iterations=5, levels=1)
    assert e < stereo_energy(cost, flat, 1.0, 2.0)
    assert (lab == truth).mean() > 0.9


def test_stereo_energy_by_hand():
    cost = np.zeros((2, 2, 4))
    cost[0, 0, 1] = 5.0
    labels = np.array([[1, 3], [1, 0]])
    # data 5; pairs: (0,0)-(0,1) |1-3|=2, (1,0)-(1,1) 1, (0,0)-(1,0) 0, (0,1)-(1,1) 3 -> trunc 2.5
    assert stereo_energy(cost, labels, 1.0, 2.5) == pytest.approx(5 + 2 + 1 + 0 + 2.5)


# --- step 4: refinement ---------------------------------------------------------------------

def test_subpixel_recovers_parabola_vertex():
    d = np.arange(10, dtype=np.float32)
    cost = ((d - 4.3) ** 2)[None, None, :].repeat(2, 0).repeat(3, 1)
    sub = subpixel_refine(winner_take_all(cost), cost)
    np.testing.assert_allclose(sub, 4.3, atol=1e-5)


def test_lr_check_removes_occluded_band():
    left, right, truth, occluded = layered_pair()
    cost = census_cost(left, right, 20, (5, 5))
    dl, dr = winner_take_all_both(box_sum_u16(cost, (5, 5)))
    checked = left_right_check(dl, dr, 1.0)
    rows = slice(4, -4)
    occ = occluded[rows]
    vis = ~occluded[rows]
    vis[:, :20] = False  # left border: candidates leave the right image
    removed = np.isnan(checked[rows])
    assert removed[occ].mean() >= 0.9
    assert (~removed[vis]).mean() >= 0.95
    err = np.abs(checked[rows] - truth[rows])[vis & ~removed]
    assert np.percentile(err, 99) <= 1.0


def test_speckle_median_and_background_fill():
    d = np.full((20, 30), 5.0, np.float32)
    d[8:10, 10:12] = 15.0                      # 4-pixel speckle
    cleaned = remove_speckles(d, max_size=10, max_diff=1.0)
    assert np.isnan(cleaned[8:10, 10:12]).all() and np.isfinite(cleaned).sum() == 600 - 4
    noisy = np.full((9, 9), 2.0, np.float32)
    noisy[4, 4] = 50.0
    noisy[0, 0] = np.nan
    med = median_filter(noisy, 3)
    assert med[4, 4] == 2.0 and np.isnan(med[0, 0])
    row = np.array([[7.0, np.nan, np.nan, 3.0, np.nan, 9.0, np.nan]], np.float32)
    np.testing.assert_array_equal(fill_invalid(row), [[7, 3, 3, 3, 3, 9, 9]])


def _opencv_speckles(d, max_size, max_diff):
    # the reference: OpenCV's filterSpeckles on the 1/16 px int16 fixed point, NaN invalid
    import cv2
    fixed = np.where(np.isnan(d), -1.0, np.round(d * 16.0)).astype(np.int16)
    cv2.filterSpeckles(fixed, -1, int(max_size), int(round(max_diff * 16)))
    out = d.copy()
    out[fixed == -1] = np.nan
    return out


def test_speckle_filter_is_opencvs_filterspeckles_bit_for_bit():
    # random maps of every kind the filter meets: noise, quantised plateaus, blocky surfaces
    # with noise, holes, values rounding to OpenCV's invalid -1 (1/16 px); several sizes and
    # tolerances, one-row and one-column maps included
    import cv2
    rng = np.random.default_rng(7)
    removed = 0
    for t in range(120):
        h, w = (int(v) for v in rng.integers(1, 50, 2))
        if t % 3 == 0:
            d = rng.uniform(0, 6, (h, w)).astype(np.float32)
        elif t % 3 == 1:
            d = (np.round(rng.uniform(0, 8, (h, w)) * 4) / 4).astype(np.float32)
        else:
            small = rng.uniform(0, 30, (max(1, h // 4), max(1, w // 4))).astype(np.float32)
            d = cv2.resize(small, (w, h), interpolation=cv2.INTER_NEAREST)
            d += rng.uniform(-0.7, 0.7, d.shape).astype(np.float32)
        d[rng.random((h, w)) < rng.uniform(0, 0.5)] = np.nan
        d[rng.random((h, w)) < 0.02] = -0.06
        for max_size, max_diff in ((1, 0.0), (5, 1.0), (20, 0.5), (100, 2.0)):
            got = remove_speckles(d, max_size, max_diff)
            want = _opencv_speckles(d, max_size, max_diff)
            np.testing.assert_array_equal(got, want)
            removed += int(np.isnan(want).sum() - np.isnan(d).sum())
    assert removed > 1000                   # the cases do remove blobs
    with pytest.raises(ValueError, match='2047'):
        remove_speckles(np.full((3, 3), 3000.0, np.float32))


@pytest.mark.parametrize('size', [3, 5])
def test_median_filter_is_the_median_of_the_valid_window_values(size):
    # brute force: every non-NaN pixel takes np.median of the non-NaN values of its window
    # clipped to the image (the 3x3 sorting network and its fall-backs included)
    rng = np.random.default_rng(3)
    for trial in range(12):
        h, w = rng.integers(1, 25, 2)
        d = rng.uniform(0, 60, (h, w)).astype(np.float32)
        if trial % 2:
            d = np.round(d)                     # ties
        d[rng.random((h, w)) < (0.0, 0.05, 0.4)[trial % 3]] = np.nan
        r = size // 2
        ref = np.full_like(d, np.nan)
        for y in range(h):
            for x in range(w):
                if not np.isnan(d[y, x]):
                    win = d[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1]
                    ref[y, x] = np.median(win[~np.isnan(win)])
        np.testing.assert_allclose(median_filter(d, size), ref, rtol=0, atol=1e-5)


# --- pipeline and evaluation ----------------------------------------------------------------

@pytest.mark.parametrize('method', ['sgm', 'sgm4', 'block_matching', 'bp', 'opencv_sgbm'])
def test_every_method_fronto_parallel_plane(method):
    left, right = shifted_pair(60, 120, 11, seed=5)
    disp = compute_disparity(left, right, method, 32)
    interior = disp[6:-6, 36:-6]      # OpenCV leaves the first D columns empty
    assert np.isfinite(interior).mean() > 0.98
    np.testing.assert_allclose(np.nanmedian(interior), 11.0, atol=0.1)
    assert (np.abs(interior - 11.0) <= 0.5).mean() > 0.97


def test_opencv_bm_is_available():
    left, right = shifted_pair(64, 128, 10, seed=6)
    disp = compute_disparity(left, right, 'opencv_bm', 32, block_size=9)
    valid = np.isfinite(disp[10:-10, 40:-10])
    assert valid.mean() > 0.9
    assert np.nanmax(np.abs(disp[10:-10, 40:-10] - 10.0)) <= 1.0
    assert {'sgm', 'sgm4', 'block_matching', 'bp', 'opencv_bm',
            'opencv_sgbm'} <= set(available_methods())


def test_compute_disparity_rejects_unknowns():
    left, right = shifted_pair()
    with pytest.raises(ValueError, match='unknown stereo method'):
        compute_disparity(left, right, 'magic')
    with pytest.raises(ValueError, match='unknown parameter'):
        compute_disparity(left, right, 'sgm', 16, p3=5)


def test_depth_and_points_of_a_plane():
    fx, B, z0 = 500.0, 0.1, 2.0
    disp = np.full((6, 8), fx * B / z0, np.float32)
    disp[0, 0] = np.nan
    depth = disparity_to_depth(disp, fx, B)
    assert np.isnan(depth[0, 0])
    np.testing.assert_allclose(depth[1:], z0, rtol=1e-6)
    pts = disparity_to_points(disp, fx, fx, 3.5, 2.5, B)
    u = fx * pts[..., 0] / pts[..., 2] + 3.5
    v = fx * pts[..., 1] / pts[..., 2] + 2.5
    np.testing.assert_allclose(u[1:], np.arange(8)[None, :].repeat(5, 0), atol=1e-4)
    np.testing.assert_allclose(v[1:, 0], np.arange(1, 6), atol=1e-4)
    with pytest.raises(ValueError, match='baseline'):
        disparity_to_depth(disp, fx, 0.0)


@pytest.mark.parametrize('method', ['block_matching', 'opencv_sgbm'])
def test_min_disparity_searches_a_band_and_reports_full_disparities(method):
    shift = 37
    left, right = shifted_pair(48, 160, shift, 4)
    disp = compute_disparity(left, right, method, 16, min_disparity=30)
    assert disp.shape == left.shape
    assert np.all(np.isnan(disp[:, :30]))                  # no match possible at d >= 30
    inner = disp[6:-6, shift + 30 + 16:-6]                 # away from the cropped borders
    assert (np.abs(inner - shift) <= 0.5).mean() > 0.95
    # the same band without the offset cannot reach the shift
    plain = compute_disparity(left, right, method, 16)
    assert np.nanmax(plain) < 16
    with pytest.raises(ValueError, match='exceeds the image width'):
        compute_disparity(left, right, method, 16, min_disparity=150)
    with pytest.raises(ValueError, match='min_disparity'):
        compute_disparity(left, right, method, 16, min_disparity=-1)


def test_surfaces_beyond_the_band_are_unknown_not_flattened_onto_its_ends():
    """
    Leave surfaces beyond the band unknown instead of flattening them onto its ends.

    The demo's band (48 .. 111 px) on a synthetic peg_in_hole frame: the background lies
    farther than the band and the near table closer; clamped to the band's first or last
    candidate they became fake flat surfaces (18 % of the valid pixels, 41 501 of them exactly
    at 48 px = 1.25 m). Now no disparity lies at the band's ends, few valid pixels lack an
    in-band truth, and the in-band pixels stay right.
    """
    from stereo_depth.synthetic import render
    left, right, info = render('peg_in_hole', 0)
    truth = info['disparity']
    lo, count = 48, 64
    disp = compute_disparity(left, right, 'block_matching', count, min_disparity=lo)
    found = np.isfinite(disp)
    ends = found & ((np.abs(disp - lo) < 0.5) | (np.abs(disp - (lo + count - 1)) < 0.5))
    assert ends.sum() == 0, f'{ends.sum()} pixels at the band ends'
    in_band = np.isfinite(truth) & (truth > lo - 0.5) & (truth < lo + count - 0.5)
    fake = found & ~in_band
    assert fake.sum() < 0.06 * found.sum(), f'{fake.sum()} of {found.sum()} without in-band truth'
    ok = found & in_band
    assert np.mean(np.abs(disp[ok] - truth[ok]) <= 1.0) > 0.9


@pytest.mark.parametrize('organized', [False, True])
def test_cloud_points_decimates_and_organises(organized):
    fx, cx, cy = 500.0, 4.5, 3.0
    depth = np.full((7, 10), 2.0, np.float32)
    depth[2, 4] = np.nan
    colours = np.arange(7 * 10 * 3, dtype=np.uint8).reshape(7, 10, 3)
    pts, rgb = cloud_points(depth, fx, fx, cx, cy, 2, organized, colours)
    full = disparity_to_points(np.where(np.isfinite(depth), fx * 0.1 / depth, np.nan), fx, fx,
                               cx, cy, 0.1)
    if organized:
        assert pts.shape == (4, 5, 3) and rgb.shape == (4, 5, 3)
        np.testing.assert_allclose(pts[np.isfinite(pts[..., 2])],
                                   full[::2, ::2][np.isfinite(pts[..., 2])], rtol=1e-6)
        assert np.isnan(pts[1, 2]).all()                   # pixel (u=4, v=2) is unknown
        np.testing.assert_array_equal(rgb, colours[::2, ::2])
    else:
        assert pts.shape == (19, 3) and np.isfinite(pts).all()
        kept = np.isfinite(depth[::2, ::2])
        np.testing.assert_allclose(pts, full[::2, ::2][kept], rtol=1e-6)
        np.testing.assert_array_equal(rgb, colours[::2, ::2][kept])
    with pytest.raises(ValueError, match='decimation'):
        cloud_points(depth, fx, fx, cx, cy, 0)


@pytest.mark.parametrize('organized', [False, True])
@pytest.mark.parametrize('colour', [False, True])
def test_packed_cloud_is_the_old_cloud_byte_for_byte(organized, colour):
    """cloud_message_data == cloud_points + xyz_to_pointcloud2, and reads back the same xyz."""
    # the message side needs ROS messages: skipped in the Noble-pinned (ROS-free) job
    pytest.importorskip('sensor_msgs.msg', reason='needs ROS (sensor_msgs), not in the '
                        'Noble-pinned venv')
    from stereo_manip_tools.conversions import (float32_fields_to_pointcloud2,
                                                pointcloud2_to_array, xyz_to_pointcloud2)
    rng = np.random.default_rng(3)
    h, w, s = 47, 61, 2                       # odd sizes: the last row/column are kept
    fx, fy, cx, cy = 525.3, 523.9, 30.7, 22.1
    depth = rng.uniform(0.3, 2.0, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.2] = np.nan
    colours = rng.integers(0, 256, (h, w, 3), dtype=np.uint8) if colour else None
    packed = cloud_message_data(depth, fx, fy, cx, cy, s, organized, colours)
    pts, rgb = cloud_points(depth, fx, fy, cx, cy, s, organized, colours)
    old = xyz_to_pointcloud2(pts.reshape(-1, 3),
                             rgb=None if rgb is None else rgb.reshape(-1, 3))
    new = float32_fields_to_pointcloud2(packed.buffer, packed.fields,
                                        is_dense=packed.is_dense)
    assert bytes(new.data) == bytes(old.data)            # bit-identical coordinates and colours
    assert [f.name for f in new.fields] == [f.name for f in old.fields]
    assert [f.offset for f in new.fields] == [f.offset for f in old.fields]
    assert new.point_step == old.point_step
    if organized:
        assert (new.height, new.width) == (24, 31) and not new.is_dense
        assert new.row_step == new.point_step * 31
    else:
        assert (new.height, new.width) == (1, int(np.isfinite(depth[::s, ::s]).sum()))
        assert new.is_dense
    xyz = pointcloud2_to_array(new)                      # round trip through the reader
    z = depth[::s, ::s]
    np.testing.assert_allclose(xyz[:, 2], z[np.isfinite(z)], rtol=1e-7)
    v, u = np.nonzero(np.isfinite(z))
    np.testing.assert_allclose(xyz[:, 0], (u * s - cx) * z[v, u] / fx, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(xyz[:, 1], (v * s - cy) * z[v, u] / fy, rtol=1e-5, atol=1e-7)
    empty = cloud_message_data(np.full((4, 4), np.nan, np.float32), fx, fy, cx, cy)
    assert empty.buffer.shape == (1, 0, 3) and empty.is_dense
    assert float32_fields_to_pointcloud2(empty.buffer, empty.fields).width == 0
    with pytest.raises(ValueError, match='decimation'):
        cloud_message_data(depth, fx, fy, cx, cy, 0)
    with pytest.raises(ValueError, match='colours'):
        cloud_message_data(depth, fx, fy, cx, cy, 1, False, np.zeros((h, w), np.uint8))


@pytest.mark.parametrize('organized', [False, True])
@pytest.mark.parametrize('decimation', [1, 2, 3])
def test_packed_cloud_from_disparity_is_the_one_from_the_depth_image(organized, decimation):
    # the node packs the cloud from the disparity (depth of the kept pixels only): the same
    # bytes as disparity_to_depth followed by cloud_message_data, doffs and holes included
    rng = np.random.default_rng(5)
    h, w = 53, 71
    fx, fy, cx, cy, baseline = 525.3, 523.9, 33.7, 25.1, 0.12
    for doffs in (0.0, -3.5, 2.25):
        disp = rng.uniform(0.0, 160.0, (h, w)).astype(np.float32)
        disp[rng.random((h, w)) < 0.2] = np.nan
        disp[0, :5] = np.float32(-doffs)              # d + doffs == 0: no depth
        colours = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        for col in (None, colours):
            want = cloud_message_data(disparity_to_depth(disp, fx, baseline, doffs), fx, fy,
                                      cx, cy, decimation, organized, col)
            got = cloud_message_data(None, fx, fy, cx, cy, decimation, organized, col,
                                     disparity=disp, baseline=baseline, doffs=doffs)
            assert got.buffer.tobytes() == want.buffer.tobytes()
            assert got.buffer.shape == want.buffer.shape and got.fields == want.fields
            assert got.is_dense == want.is_dense
            assert want.buffer.shape[1] > 10
    with pytest.raises(ValueError, match='either'):
        cloud_message_data(disp, fx, fy, cx, cy, disparity=disp, baseline=baseline)
    with pytest.raises(ValueError, match='baseline'):
        cloud_message_data(None, fx, fy, cx, cy, disparity=disp, baseline=0.0)


def test_evaluation_metrics_by_hand():
    truth = np.array([[10.0, 10.0, 10.0, np.inf], [10.0, 10.0, 10.0, 10.0]])
    est = np.array([[10.5, 11.5, 13.0, 1.0], [np.nan, 10.0, 4.0, 10.0]])
    m = evaluate_disparity(est, truth)
    assert m['n_evaluated'] == 7
    assert m['invalid'] == pytest.approx(1 / 7)
    assert m['bad-1.0'] == pytest.approx(4 / 7)    # 1.5, 3, 6 and the missing one
    assert m['bad-2.0'] == pytest.approx(3 / 7)
    assert m['bad-2.0_valid'] == pytest.approx(2 / 6)
    assert m['avgerr'] == pytest.approx((0.5 + 1.5 + 3 + 0 + 6 + 0) / 6)
    mask = np.ones_like(truth, bool)
    mask[1] = False
    assert evaluate_disparity(est, truth, mask)['bad-2.0'] == pytest.approx(1 / 3)


def test_nonoccluded_mask_finds_the_occluded_band():
    _, _, truth, occluded = layered_pair(d_back=4, d_front=12, front=(30, 60))
    mask = nonoccluded_mask(truth)
    assert not mask[:, 22:30].any()            # the 8-pixel band hidden by the foreground
    assert not mask[:, :4].any()               # lands left of the right image
    assert mask[:, 4:22].all() and mask[:, 30:].all()
    np.testing.assert_array_equal(mask, ~occluded & (np.arange(96) >= 4)[None, :])


@settings(max_examples=8, deadline=None)
@given(shift=st.integers(0, 20), seed=st.integers(0, 1000))
def test_block_matching_recovers_any_integer_shift(shift, seed):
    left, right = shifted_pair(32, 72, shift, seed)
    dl, dr = census_block_matching(left, right, 24, (5, 5), (5, 5))
    np.testing.assert_array_equal(np.rint(dl[4:-4, shift + 4:-4]), shift)
    np.testing.assert_array_equal(dr[4:-4, 4:-shift - 4], shift)


def test_pfm_round_trip(tmp_path):
    from stereo_depth.evaluation import read_pfm, write_pfm

    img = np.arange(12, dtype=np.float32).reshape(3, 4)
    img[0, 1] = np.inf
    write_pfm(tmp_path / 'd.pfm', img)
    np.testing.assert_array_equal(read_pfm(tmp_path / 'd.pfm'), img)


@pytest.mark.process
def test_evaluate_disparity_executable(tmp_path):
    import json
    import subprocess

    from stereo_depth.evaluation import write_pfm
    from stereo_manip_tools.testing import executable_path

    truth = np.full((20, 30), 10.0, np.float32)
    est = truth.copy()
    est[:5] = 13.0          # 25 % bad-2
    est[5, :] = np.nan      # 5 % missing
    write_pfm(tmp_path / 'gt.pfm', truth)
    np.save(tmp_path / 'est.npy', est)
    exe = str(executable_path('stereo_depth', 'evaluate_disparity'))
    res = subprocess.run([exe, str(tmp_path / 'est.npy'), str(tmp_path / 'gt.pfm'), '--json'],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    metrics = json.loads(res.stdout)
    assert metrics['bad-2.0'] == pytest.approx(0.30)
    assert metrics['invalid'] == pytest.approx(0.05)
    bad = subprocess.run([exe, str(tmp_path / 'missing.pfm'), str(tmp_path / 'gt.pfm')],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and 'no such file' in bad.stderr


@pytest.mark.parametrize('shape, census_window, window, nd', [
    ((7, 40), (5, 5), (7, 7), 16), ((9, 50), (5, 5), (3, 9), 16),
    ((30, 60), (3, 3), (5, 11), 16), ((2, 30), (3, 3), (5, 5), 16),
    ((24, 150), (5, 5), (7, 7), 112), ((20, 90), (9, 7), (5, 5), 33),
    ((16, 70), (7, 7), (3, 3), 64), ((11, 45), (5, 5), (7, 7), 45)])
@pytest.mark.parametrize('dtype', [np.float32, np.uint8])
def test_fused_block_matching_equals_step_by_step_at_borders(shape, census_window, window, nd,
                                                             dtype):
    # The fused kernel (census byte planes, candidates padded to a multiple of 32, packed
    # minima) against the cost volume -> box sums -> WTA path: integer right-view disparities
    # and the left view's subpixel values exactly equal, on random images.
    rng = np.random.default_rng(7)
    left = rng.integers(0, 255, shape).astype(dtype)
    right = rng.integers(0, 255, shape).astype(dtype)
    ref = winner_take_all_both(box_sum_u16(census_cost(left, right, nd, census_window), window))
    fused = census_block_matching(left, right, nd, census_window, window)
    np.testing.assert_array_equal(fused[0], ref[0])
    np.testing.assert_array_equal(fused[1], ref[1])


def test_fused_block_matching_uniqueness_and_row_chunks_equal_step_by_step():
    rng = np.random.default_rng(11)
    left = rng.integers(0, 255, (26, 80)).astype(np.uint8)
    right = np.ascontiguousarray(np.roll(left, -5, axis=1))
    right[:, ::7] = rng.integers(0, 255, (26, 12))       # some ambiguous matches
    cost = box_sum_u16(census_cost(left, right, 20, (5, 5)), (5, 5))
    for u in (0.0, 0.05):
        ref = winner_take_all_both(cost, u)
        fused = census_block_matching(left, right, 20, (5, 5), (5, 5), uniqueness=u)
        np.testing.assert_array_equal(fused[0], ref[0])
        np.testing.assert_array_equal(fused[1], ref[1])
    assert np.isnan(winner_take_all_both(cost, 0.05)[0]).any()     # the test is not vacuous
    from stereo_depth.matching_cost import census_planes as planes
    from stereo_depth.optimization import _census_box_wta
    ref = winner_take_all_both(cost)
    for chunks in (2, 5):      # rows split into independent chunks (one per numba thread)
        out = _census_box_wta(planes(left, (5, 5)), planes(right, (5, 5)), 20, 2, 2,
                              np.uint8(24), chunks, 0.0)
        np.testing.assert_array_equal(out[0], ref[0])
        np.testing.assert_array_equal(out[1], ref[1])
