import math

import numpy as np
import pytest
from conftest import real

from splatstream import sh
from splatstream.camera import look_at, suggested_camera
from splatstream.gaussians import Gaussians, logit
from splatstream.io import read_gaussians
from splatstream.render_ref import preprocess, render, render_with_alpha


def make(positions, scales, opacities, colors, rotations=None, rest=None) -> Gaussians:
    n = len(positions)
    rot = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)) if rotations is None else rotations
    dc = (np.asarray(colors, np.float64) - 0.5) / sh.SH_C0
    rest = np.zeros((n, 0, 3)) if rest is None else rest
    return Gaussians(np.asarray(positions, np.float64), rot, np.log(np.asarray(scales, np.float64)),
                     logit(np.asarray(opacities, np.float64)), dc, rest)


def test_single_isotropic_gaussian_matches_analytic():
    s, d, size = 0.05, 5.0, 64
    g = make([[0, 0, 0]], [[s, s, s]], [0.8], [[1.0, 0.5, 0.25]])
    cam = look_at((0, 0, d), (0, 0, 0), up=(0, 1, 0), width=size, height=size)
    img = render(g, cam)
    f = cam.focal[1]
    var = (f * s / d) ** 2 + 0.3
    c = (size - 1) / 2.0  # pixel-index coordinates of the projected centre
    yy, xx = np.mgrid[0:size, 0:size]
    r2 = (xx - c) ** 2 + (yy - c) ** 2
    alpha = np.minimum(0.99, float(g.opacities[0]) * np.exp(-0.5 * r2 / var))
    radius = math.ceil(3 * math.sqrt(var))
    assert radius < size / 2 - 16  # the splat's tiles do not reach the border tiles
    inside = alpha >= 1 / 255
    rgb = g.base_colors[0].astype(np.float64)
    expected = np.where(inside[..., None], alpha[..., None] * rgb, 0.0)
    sample = [(c - 0.5, c - 0.5), (c + 0.5, c + 3.5), (c - 6.5, c + 0.5), (0, 0), (c + 2.5, c - 4.5)]
    for y, x in sample:
        y, x = int(y), int(x)
        np.testing.assert_allclose(img[y, x], expected[y, x], rtol=1e-5, atol=1e-7)
    # the image is symmetric about its centre
    np.testing.assert_allclose(img, img[::-1, ::-1], atol=1e-6)
    assert img[int(c), int(c), 0] > 0.5


def test_depth_order_not_file_order():
    cam = look_at((0, 0, 5), (0, 0, 0), up=(0, 1, 0), width=33, height=33)
    front = ([0, 0, 1.0], [0.3] * 3, 0.9, [1.0, 0.0, 0.0])
    back = ([0, 0, -1.0], [0.3] * 3, 0.9, [0.0, 0.0, 1.0])
    imgs = []
    for order in ([front, back], [back, front]):
        g = make(*[[o[i] for o in order] for i in range(4)])
        imgs.append(render(g, cam))
    np.testing.assert_array_equal(imgs[0], imgs[1])
    centre = imgs[0][16, 16]
    assert centre[0] == pytest.approx(0.9, abs=1e-3)  # red, in front: alpha 0.9 at T = 1
    assert centre[2] == pytest.approx(0.1 * 0.9, abs=2e-3)  # blue behind, T = 0.1


def test_transmittance_cutoff_excludes_the_splat_that_would_cross_it():
    size = 33  # odd: the projected centre is the centre of pixel 16
    cam = look_at((0, 0, 10), (0, 0, 0), up=(0, 1, 0), width=size, height=size)
    zs = [1.0, 0.5, 0.0, -0.5, -1.0]
    cols = [[0.1, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.3], [100.0, 100.0, 100.0], [50.0, 50.0, 50.0]]
    g = make([[0, 0, z] for z in zs], [[0.2] * 3] * 5, [0.95] * 5, cols)
    img, cover = render_with_alpha(g, cam)
    a = g.opacities.astype(np.float64)
    t, expected = 1.0, np.zeros(3)
    for i in range(5):
        if t * (1 - a[i]) < 1e-4:
            break
        expected += np.asarray(g.base_colors[i], np.float64) * a[i] * t
        t *= 1 - a[i]
    assert i == 3  # 0.05^3 = 1.25e-4 survives, 0.05^4 does not
    np.testing.assert_allclose(img[16, 16], expected, rtol=0, atol=1e-6)
    assert 1 - cover[16, 16] == pytest.approx(t, rel=1e-4)
    assert img[16, 16].max() < 1.0  # the bright splats behind never show


def test_background_fills_remaining_transmittance():
    cam = look_at((0, 0, 5), (0, 0, 0), up=(0, 1, 0), width=32, height=32)
    g = make([[0, 0, 0]], [[0.05] * 3], [0.5], [[0.0, 0.0, 0.0]])
    img = render(g, cam, background=(1.0, 1.0, 1.0))
    assert img[0, 0] == pytest.approx([1.0, 1.0, 1.0])
    assert img[16, 16, 0] == pytest.approx(1 - float(g.opacities[0]) * math.exp(-0.5 * 0.5 / (
        (cam.focal[1] * 0.05 / 5) ** 2 + 0.3)), rel=1e-5)


def test_sh_eval_hand_computed():
    dc = np.array([[0.1, 0.2, 0.3]])
    rest = np.zeros((1, 15, 3))
    rest[0, 1] = [1.0, 0.0, 0.0]     # z term of band 1
    rest[0, 5] = [0.0, 1.0, 0.0]     # (2zz - xx - yy) term of band 2
    rest[0, 11] = [0.0, 0.0, 1.0]    # z (2zz - 3xx - 3yy) term of band 3
    rest[0, 14] = [5.0, 5.0, 5.0]    # x (xx - 3yy): zero along +z
    up = sh.eval_sh(dc, rest, np.array([[0.0, 0.0, 1.0]]))
    expected = np.array([0.5 + 0.28209479177387814 * 0.1 + 0.4886025119029199,
                         0.5 + 0.28209479177387814 * 0.2 + 2 * 0.31539156525252005,
                         0.5 + 0.28209479177387814 * 0.3 + 2 * 0.3731763325901154])
    np.testing.assert_allclose(up[0], expected, rtol=1e-12)
    # along +x: band 1 z term vanishes, band 2 gives -C2[2], band 3 x(xx-3yy) gives C3[6] * 5
    side = sh.eval_sh(dc, rest, np.array([[1.0, 0.0, 0.0]]))
    expected = np.array([0.5 + 0.28209479177387814 * 0.1 - 0.5900435899266435 * 5,
                         0.5 + 0.28209479177387814 * 0.2 - 0.31539156525252005 - 0.5900435899266435 * 5,
                         0.5 + 0.28209479177387814 * 0.3 - 0.5900435899266435 * 5])
    np.testing.assert_allclose(side[0], np.maximum(expected, 0.0), rtol=1e-12)
    assert side[0].min() == 0.0  # clamped at zero
    big = sh.eval_sh(np.array([[10.0, 10.0, 10.0]]), np.zeros((1, 0, 3)), np.array([[0.0, 0.0, 1.0]]))
    assert big[0, 0] > 1.0  # no upper clamp
    # lowering the degree drops bands
    lowered = sh.eval_sh(dc, rest, np.array([[0.0, 0.0, 1.0]]), degree=1)
    np.testing.assert_allclose(lowered[0, 1:], 0.5 + 0.28209479177387814 * dc[0, 1:], rtol=1e-12)


def test_sh_basis_expressions_match_numpy():
    rng = np.random.default_rng(3)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    env = {"x": x, "y": y, "z": z, "SH_C0": sh.SH_C0, "SH_C1": sh.SH_C1, "SH_C2": sh.SH_C2, "SH_C3": sh.SH_C3}
    basis = sh.sh_basis(d, 3)
    assert len(sh.SH_BASIS) == 16
    for k, (const, poly) in enumerate(sh.SH_BASIS):
        value = eval(f"({const}) * ({poly})", {}, env) * np.ones(len(d))  # our own table
        np.testing.assert_allclose(value, basis[:, k], rtol=1e-12, atol=1e-15)
    # the basis is orthonormal on the sphere: integrate with many random directions
    u = rng.normal(size=(200000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    b = sh.sh_basis(u, 3)
    gram = 4 * np.pi * (b.T @ b) / len(u)
    np.testing.assert_allclose(gram, np.eye(16), atol=0.03)


# --- an independent, straightforward implementation: one splat and one pixel at a time ----------------------------

def _naive_render(g: Gaussians, cam, background=(0.0, 0.0, 0.0)) -> np.ndarray:
    w_img, h_img = cam.width, cam.height
    f = cam.focal[0]
    fwd = np.subtract(cam.target, cam.eye)
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, cam.up)
    right /= np.linalg.norm(right)
    down = -np.cross(right, fwd)
    rot_w = np.stack([right, down, fwd])
    tan_y = math.tan(math.radians(cam.fov_y_deg) / 2)
    tan_x = tan_y * w_img / h_img
    splats = []
    for i in range(len(g)):
        t = rot_w @ (g.positions[i].astype(np.float64) - np.asarray(cam.eye))
        if t[2] <= cam.near:
            continue
        qw, qx, qy, qz = g.rotations[i].astype(np.float64)
        r = np.array([
            [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)],
            [2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)],
            [2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)]])
        m = r @ np.diag(np.exp(g.log_scales[i].astype(np.float64)))
        sigma = m @ m.T
        tx = min(1.3 * tan_x, max(-1.3 * tan_x, t[0] / t[2])) * t[2]
        ty = min(1.3 * tan_y, max(-1.3 * tan_y, t[1] / t[2])) * t[2]
        jac = np.array([[f / t[2], 0, -f * tx / t[2] ** 2], [0, f / t[2], -f * ty / t[2] ** 2]])
        cov = jac @ rot_w @ sigma @ rot_w.T @ jac.T + 0.3 * np.eye(2)
        det = cov[0, 0] * cov[1, 1] - cov[0, 1] ** 2
        if det == 0:
            continue
        conic = np.linalg.inv(cov)
        mid = 0.5 * (cov[0, 0] + cov[1, 1])
        lam = mid + math.sqrt(max(0.1, mid * mid - det))
        radius = math.ceil(3 * math.sqrt(lam))
        px = ((t[0] / (t[2] * tan_x) + 1) * w_img - 1) / 2
        py = ((t[1] / (t[2] * tan_y) + 1) * h_img - 1) / 2
        gx, gy = -(-w_img // 16), -(-h_img // 16)
        x0 = min(gx, max(0, int((px - radius) / 16)))
        y0 = min(gy, max(0, int((py - radius) / 16)))
        x1 = min(gx, max(0, int((px + radius + 15) / 16)))
        y1 = min(gy, max(0, int((py + radius + 15) / 16)))
        if radius == 0 or (x1 - x0) * (y1 - y0) == 0:
            continue
        d = g.positions[i].astype(np.float64) - np.asarray(cam.eye)
        colour = sh.eval_sh(g.sh_dc[i:i + 1], g.sh_rest[i:i + 1], (d / np.linalg.norm(d))[None])[0]
        opacity = 1 / (1 + math.exp(-float(g.opacity_logits[i])))
        splats.append((t[2], i, px, py, conic, opacity, colour, (x0, y0, x1, y1)))
    splats.sort(key=lambda s: (s[0], s[1]))
    img = np.zeros((h_img, w_img, 3))
    for row in range(h_img):
        for col in range(w_img):
            t_acc, c_acc = 1.0, np.zeros(3)
            for _, _, px, py, conic, opacity, colour, (x0, y0, x1, y1) in splats:
                if not (x0 <= col // 16 < x1 and y0 <= row // 16 < y1):
                    continue
                dx, dy = px - col, py - row
                power = -0.5 * (conic[0, 0] * dx * dx + conic[1, 1] * dy * dy) - conic[0, 1] * dx * dy
                if power > 0:
                    continue
                alpha = min(0.99, opacity * math.exp(power))
                if alpha < 1 / 255:
                    continue
                if t_acc * (1 - alpha) < 1e-4:
                    break
                c_acc += colour * alpha * t_acc
                t_acc *= 1 - alpha
            img[row, col] = c_acc + t_acc * np.asarray(background)
    return img


def test_matches_naive_per_pixel_loop():
    rng = np.random.default_rng(7)
    n = 60
    pos = rng.normal(scale=0.6, size=(n, 3))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    scales = np.exp(rng.uniform(-3.5, -1.0, size=(n, 3)))
    opac = rng.uniform(0.2, 1.0, size=n)
    opac[:5] = 0.999  # saturate some pixels
    colors = rng.uniform(0, 1, size=(n, 3))
    rest = rng.normal(scale=0.3, size=(n, 15, 3))
    g = make(pos, scales, opac, colors, rotations=q, rest=rest)
    g.positions[7] = g.positions[8]  # an exact depth tie: file order decides
    cam = look_at((2.5, -2.0, 1.2), (0.1, 0.0, 0.0), up=(0, 0, 1), width=40, height=27, fov_y_deg=55)
    got = render(g, cam, background=(0.2, 0.1, 0.0))
    want = _naive_render(g, cam, background=(0.2, 0.1, 0.0))
    assert want.max() > 0.5
    np.testing.assert_allclose(got, want, rtol=0, atol=2e-6)  # float32 output of float64 arithmetic


def test_off_screen_and_behind_camera_are_culled():
    cam = look_at((0, 0, 5), (0, 0, 0), up=(0, 1, 0), width=32, height=32)
    g = make([[0, 0, 6.0], [0, 0, 5.1], [50, 0, 0]], [[0.1] * 3] * 3, [0.9] * 3, [[1, 1, 1]] * 3)
    p = preprocess(g, cam)
    assert len(p.index) == 0
    assert render(g, cam).max() == 0.0


@pytest.mark.parametrize("name", ["fruit_drops_sh3.ply", "donut_sh0_no_normals.ply"])
def test_real_scenes_render(name):
    g = read_gaussians(real(name))
    cam = suggested_camera(g.positions, width=96, height=64)
    img = render(g, cam)
    assert img.shape == (64, 96, 3) and img.dtype == np.float32
    assert np.isfinite(img).all()
    assert img.mean() > 0.05
    assert (img.max(axis=2) > 0.1).mean() > 0.1  # a good part of the view is covered
    assert img.std() > 0.02


def test_tile_lists_sort_key_gives_the_stable_depth_order():
    # tile_lists' 16-bit sort key gives the int64 key's stable order
    from splatstream.camera import scene_orbit_views
    from splatstream.render_ref import TILE, tile_lists

    g = read_gaussians(real("fruit_drops_sh3.ply"))
    for cam in [suggested_camera(g.positions, width=96, height=64),
                scene_orbit_views(g.positions, 1, 600, 400, elevation_deg=25.0)[0]]:
        a = preprocess(g, cam)
        assert len(a.index) > 100 and a.color.shape == (len(a.index), 3)
        grid_x, grid_y = -(-cam.width // TILE), -(-cam.height // TILE)
        ids, offsets = tile_lists(a, grid_x, grid_y)
        w = a.rect_max[:, 0] - a.rect_min[:, 0]
        h = a.rect_max[:, 1] - a.rect_min[:, 1]
        want = [i for ty in range(grid_y) for tx in range(grid_x) for i in range(len(w))
                if a.rect_min[i, 0] <= tx < a.rect_max[i, 0] and a.rect_min[i, 1] <= ty < a.rect_max[i, 1]]
        assert ids.tolist() == want and offsets[-1] == len(want) == int((w * h).sum())
