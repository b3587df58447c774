"""The synthetic scene's own mesh rasterizer: coverage, depth, interpolation, occlusion,
near-plane clipping, and agreement of the numba kernel with the numpy reference."""

from __future__ import annotations

import numpy as np
import pytest

from cogs.data.synth.raster import interpolate, rasterize, rasterize_reference, scale_intrinsics
from cogs.data.synth.render import majority_label

W, H = 40, 30
K = np.array([[30.0, 0.0, W / 2], [0.0, 30.0, H / 2], [0.0, 0.0, 1.0]])


def _quad(x0, x1, y0, y1, z):
    """Camera-space rectangle at constant depth whose projection is pixel box [x0,x1]x[y0,y1]."""
    px = lambda u: (u - K[0, 2]) / K[0, 0] * z  # noqa: E731
    py = lambda v: (v - K[1, 2]) / K[1, 1] * z  # noqa: E731
    v = np.array([[px(x0), py(y0), z], [px(x1), py(y0), z], [px(x1), py(y1), z], [px(x0), py(y1), z]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _rays(width=W, height=H, KK=K):
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    return np.stack([(jj - KK[0, 2]) / KK[0, 0], (ii - KK[1, 2]) / KK[1, 1], np.ones_like(jj)], -1)


def test_pixel_aligned_quad_covers_exactly_its_pixels_once():
    v, f = _quad(5.0, 17.0, 4.0, 13.0, 2.0)
    r = rasterize(v, f, K, W, H)
    expected = np.zeros((H, W), bool)
    expected[4:13, 5:17] = True
    assert np.array_equal(r.tri >= 0, expected)  # no cracks along the shared diagonal
    assert np.allclose(r.depth[expected], 2.0)
    # Both triangles drew pixels; a pixel centre on the diagonal went to exactly one.
    assert set(np.unique(r.tri[expected])) == {0, 1}


def test_adjacent_quads_share_their_edge_without_gaps_or_overlap():
    v1, f1 = _quad(5.0, 12.0, 4.0, 13.0, 2.0)
    v2, f2 = _quad(12.0, 20.0, 4.0, 13.0, 2.0)
    r = rasterize(np.concatenate([v1, v2]), np.concatenate([f1, f2 + 4]), K, W, H)
    assert (r.tri[4:13, 5:12] < 2).all() and (r.tri[4:13, 12:20] >= 2).all()
    assert (r.tri[4:13, 5:20] >= 0).all()


def test_coverage_of_a_triangle_matches_its_area():
    # A large triangle: covered pixel count equals its area up to the boundary pixels.
    z = 3.0
    pix = np.array([[3.3, 2.1], [36.7, 8.4], [11.2, 27.9]])
    v = np.concatenate([(pix - K[:2, 2]) / K[0, 0] * z, np.full((3, 1), z)], axis=1)
    r = rasterize(v, np.array([[0, 1, 2]]), K, W, H)
    a, b, c = pix
    area = 0.5 * abs((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))
    perimeter = sum(np.linalg.norm(p - q) for p, q in ((a, b), (b, c), (c, a)))
    assert abs((r.tri >= 0).sum() - area) < 0.5 * perimeter


def _slanted_plane():
    # Plane through (0, 0, 2) with normal n; a big quad on it in front of the camera.
    n = np.array([0.3, -0.4, 1.0])
    n /= np.linalg.norm(n)
    p0 = np.array([0.0, 0.0, 2.0])
    e1 = np.cross(n, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    v = np.array([p0 + s * e1 + t * e2 for s, t in ((-3, -3), (3, -3), (3, 3), (-3, 3))])
    return v, np.array([[0, 1, 2], [0, 2, 3]]), n, p0


def test_depth_is_camera_z_of_the_ray_plane_intersection():
    v, f, n, p0 = _slanted_plane()
    r = rasterize(v, f, K, W, H)
    d = _rays()
    t = (n @ p0) / (d @ n)  # ray x = t d, and d.z = 1, so camera z = t
    hit = r.tri >= 0
    assert hit.mean() > 0.9
    np.testing.assert_allclose(r.depth[hit], t[hit], rtol=1e-9)


def test_interpolation_is_perspective_correct():
    # Interpolating the vertices' own 3D positions must give the exact surface point; an
    # affine (screen-space) interpolation is off by centimetres on this slanted quad.
    v, f, n, p0 = _slanted_plane()
    r = rasterize(v, f, K, W, H)
    pos = interpolate(r, f, v)
    hit = r.tri >= 0
    exact = _rays() * r.depth[..., None]
    np.testing.assert_allclose(pos[hit], exact[hit], atol=2e-5)


def test_nearer_surface_wins_regardless_of_draw_order():
    va, fa = _quad(2.0, 30.0, 2.0, 25.0, 3.0)
    vb, fb = _quad(10.0, 38.0, 5.0, 28.0, 1.5)
    for verts, faces, near_ids in (
        (np.concatenate([va, vb]), np.concatenate([fa, fb + 4]), {2, 3}),
        (np.concatenate([vb, va]), np.concatenate([fb, fa + 4]), {0, 1}),
    ):
        r = rasterize(verts, faces, K, W, H)
        overlap = np.zeros((H, W), bool)
        overlap[5:25, 10:30] = True
        assert set(np.unique(r.tri[overlap])) <= near_ids
        assert np.allclose(r.depth[overlap], 1.5)


def test_near_plane_clips_a_floor_that_passes_behind_the_camera():
    # A floor 1.5 m below the camera (y down in OpenCV) from 5 m behind to 20 m ahead.
    y = 1.5
    v = np.array([[-10, y, -5.0], [10, y, -5.0], [10, y, 20.0], [-10, y, 20.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    near = 0.1
    r = rasterize(v, f, K, W, H, near=near)
    d = _rays()
    below = d[..., 1] > 0
    t = y / np.where(below, d[..., 1], 1.0)
    visible = below & (t <= 20.0) & (np.abs(t * d[..., 0]) <= 10.0)
    assert np.array_equal(r.tri >= 0, visible)
    np.testing.assert_allclose(r.depth[visible], t[visible], rtol=1e-9)
    assert (r.depth[visible] >= near).all()
    # Entirely behind the camera: nothing drawn.
    r2 = rasterize(v * np.array([1, 1, -1]) + np.array([0, 0, -30.0]), f, K, W, H, near=near)
    assert (r2.tri < 0).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_numba_kernel_matches_numpy_reference(seed):
    rng = np.random.default_rng(seed)
    v = rng.uniform([-1.5, -1.2, -0.8], [1.5, 1.2, 4.0], (90, 3))  # some vertices behind the camera
    f = rng.integers(0, 90, (70, 3))
    a = rasterize(v, f, K, W, H, near=0.1)
    b = rasterize_reference(v, f, K, W, H, near=0.1)
    assert np.array_equal(a.tri, b.tri)
    hit = a.tri >= 0
    np.testing.assert_allclose(a.depth[hit], b.depth[hit], rtol=1e-12)
    np.testing.assert_allclose(a.bary[hit], b.bary[hit], atol=1e-6)


def test_supersampled_pixel_centres_coincide_with_output_pixel_centres():
    ss = 3
    Kss = scale_intrinsics(K, ss)
    fine = _rays(W * ss, H * ss, Kss)[ss // 2::ss, ss // 2::ss]
    np.testing.assert_allclose(fine, _rays(), atol=1e-12)


def test_majority_label_breaks_ties_with_the_centre_sample():
    block = np.array([[1, 1, 1], [1, 2, 2], [0, 2, 2]], dtype=np.int8)  # 4 human, 4 object
    assert majority_label(block, 3)[0, 0] == 2
    block[1, 1] = 1  # now 5 human
    assert majority_label(block, 3)[0, 0] == 1
