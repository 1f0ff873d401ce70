"""The virtual RGB-D camera (cosserat_ros.camera) against independent references: the
closed-form depth of a flat sheet and of each shape, and a numpy ray cast of the same
triangles written here with another algorithm (plane hit, then edge-side tests) than the
renderer's (Moeller-Trumbore)."""
import math

import numpy as np
import pytest

from cosserat_ros.simulator import ClothSimulator, Material
from cosserat_ros.camera import Camera, FABRIC, BACKGROUND, quaternion_looking_at
from cosserat_ros.core.contact import rotation_matrix
from cosserat_ros.mesh import grid_mesh

CLOTH = Material(zeta=50.0, xi=2e-5, phi=1e-6, density=0.2, damping=0.1)
DOWN = (1.0, 0.0, 0.0, 0.0)          # optical z = world -z, image x = world x


def _sim(n=10, side=1.0):
    return ClothSimulator(grid_mesh(n, n, width=side, height=side), CLOTH, dt=1e-4,
                          check_dt=False)


def _world_rays(cam):
    """Unit-less ray directions K^-1 (u, v, 1) of every pixel, in the world, from K alone."""
    K = cam.intrinsics
    h, w = cam.height, cam.width
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    d = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    return d @ rotation_matrix(cam.orientation).T, d


def _reference_cast(cam, x, faces):
    """Depth along the optical axis of the nearest triangle per pixel: each ray meets each
    triangle's plane, and the hit is inside when it is on the inner side of all three
    edges (same sign of the edge normals' dot products with the face normal)."""
    dw, dc = _world_rays(cam)
    o = cam.position
    a, b, c = x[faces[:, 0]], x[faces[:, 1]], x[faces[:, 2]]
    n = np.cross(b - a, c - a)                                   # (m, 3)
    rays = dw.reshape(-1, 3)
    denom = rays @ n.T                                           # (p, m)
    with np.errstate(divide='ignore', invalid='ignore'):
        s = ((a - o) * n).sum(1)[None, :] / denom                # ray parameter
    best = np.full(len(rays), np.inf)
    for chunk in range(0, len(rays), 512):
        r = rays[chunk:chunk + 512]
        sc = s[chunk:chunk + 512]
        p = o + sc[:, :, None] * r[:, None, :]                   # (q, m, 3)
        inside = np.ones(sc.shape, bool)
        for e0, e1 in ((a, b), (b, c), (c, a)):
            inside &= (np.cross(e1 - e0, p - e0) * n).sum(-1) >= 0
        z = sc * dc.reshape(-1, 3)[chunk:chunk + 512, 2:3]       # depth = s d_z (d_z = 1)
        ok = inside & np.isfinite(sc) & (z >= cam.near) & (z <= cam.far)
        best[chunk:chunk + 512] = np.where(ok, z, np.inf).min(1)
    out = best.reshape(cam.height, cam.width)
    out[~np.isfinite(out)] = np.nan
    return out


# ------------------------------------------------------------------ conventions
def test_intrinsics_follow_the_ros_pinhole_convention():
    cam = Camera(640, 480, 60.0, (0, 0, 1), DOWN)
    K = cam.intrinsics
    f = 240.0 / math.tan(math.radians(30.0))
    np.testing.assert_allclose(K, [[f, 0, 319.5], [0, f, 239.5], [0, 0, 1]])
    # the top and bottom rows' rays span the vertical field of view
    top = np.linalg.solve(K, [319.5, -0.5, 1.0])
    assert math.degrees(2 * math.atan(-top[1])) == pytest.approx(60.0)


def test_looking_at_points_the_optical_axis_and_keeps_up_up():
    q = quaternion_looking_at((1.0, -2.0, 0.5), (0.0, 0.0, 0.0))
    R = rotation_matrix(q)
    z = np.array([-1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
    np.testing.assert_allclose(R[:, 2], z, atol=1e-12)
    assert R[:, 1] @ [0, 0, 1] < 0                    # image y (down) against world up
    assert abs(R[:, 0] @ [0, 0, 1]) < 1e-12            # image x horizontal
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    # straight down: up is parallel to the view, any horizontal image x will do
    R = rotation_matrix(quaternion_looking_at((0, 0, 2), (0, 0, 0)))
    np.testing.assert_allclose(R[:, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)


@pytest.mark.parametrize('kwargs, message', [
    (dict(width=0), 'width must be in'), (dict(height=5000), 'height must be in'),
    (dict(width=4096, height=4096), 'pixels, at most'), (dict(width=2.5), 'integer'),
    (dict(fov=0.0), 'fov must be in'), (dict(fov=180.0), 'fov must be in'),
    (dict(fov=float('nan')), 'fov must be finite'),
    (dict(orientation=(0, 0, 0, 2)), 'unit quaternion'),
    (dict(position=(0, float('inf'), 0)), 'finite'),
    (dict(near=0.0), 'near < far'), (dict(near=2.0, far=1.0), 'near < far'),
])
def test_bad_arguments_are_refused_with_the_reason(kwargs, message):
    args = dict(width=64, height=48, fov=60.0, position=(0, 0, 1), orientation=DOWN)
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        Camera(**args)


# ------------------------------------------------------------------ exactness
def test_flat_cloth_depth_and_silhouette_match_the_closed_form():
    sim = _sim(10, side=1.0)
    z0, height = 0.3, 2.0
    x = sim.positions
    x[:, 2] = z0
    sim.set_positions(x)
    cam = Camera(160, 120, 45.0, (0.013, -0.021, height), DOWN)
    depth, rgb = cam.render(sim)
    assert depth.dtype == np.float32 and depth.shape == (120, 160)
    assert rgb.dtype == np.uint8 and rgb.shape == (120, 160, 3)
    hit = np.isfinite(depth)
    np.testing.assert_allclose(depth[hit], height - z0, atol=1e-5)
    # the silhouette: the pixels whose ray meets |x|, |y| <= 0.5 at z0
    dw, _ = _world_rays(cam)
    s = (z0 - height) / dw[..., 2]
    px = cam.position[0] + s * dw[..., 0]
    py = cam.position[1] + s * dw[..., 1]
    inside = (np.abs(px) <= 0.5) & (np.abs(py) <= 0.5)
    f = cam.intrinsics[0, 0]
    border = (np.abs(np.abs(px) - 0.5) < 1.0 * (height - z0) / f) | \
             (np.abs(np.abs(py) - 0.5) < 1.0 * (height - z0) / f)
    assert np.array_equal(hit[~border], inside[~border])
    # the covered area within one pixel row of the border
    area_px = (1.0 * f / (height - z0)) ** 2
    perimeter_px = 4.0 * f / (height - z0)
    assert abs(hit.sum() - area_px) <= perimeter_px
    # colour: the fabric where the cloth is, facing the light head-on at the centre
    centre = rgb[60, 80].astype(float) / 255
    np.testing.assert_allclose(centre, FABRIC, atol=0.02)
    assert np.all(rgb[~hit] == np.round(255 * np.array(BACKGROUND)).astype(np.uint8))


def test_flat_cloth_is_seen_from_below_too():
    sim = _sim(6)
    cam = Camera.looking_at(64, 48, 50.0, (0.05, 0.02, -1.0), (0.0, 0.0, 0.0))
    depth, rgb = cam.render(sim)
    dw, _ = _world_rays(cam)
    s = -cam.position[2] / dw[24, 32, 2]               # the ray meets z = 0 at s d
    assert depth[24, 32] == pytest.approx(s, abs=1e-6)
    np.testing.assert_allclose(rgb[24, 32] / 255, FABRIC, atol=0.03)


def _crumpled(sim, seed=3):
    """The sheet folded over itself along x = 0.15 (two layers), waved and jittered."""
    rng = np.random.default_rng(seed)
    x = sim.positions
    fold = x[:, 0] > 0.15
    x[fold, 0] = 0.3 - x[fold, 0]
    x[fold, 2] = 0.04 + 0.02 * np.sin(7 * x[fold, 1])
    x[:, 2] += 0.03 * np.sin(5 * x[:, 0]) * np.cos(4 * x[:, 1])
    x += rng.uniform(-0.004, 0.004, x.shape)
    sim.set_positions(x)
    return x


@pytest.mark.parametrize('eye, target', [
    ((0.0, 0.0, 1.2), (0.0, 0.0, 0.0)),
    ((0.7, -0.5, 0.6), (0.0, 0.1, 0.0)),
    ((-0.4, 0.3, -0.8), (0.0, 0.0, 0.02)),            # from below
    ((0.05, 0.0, 0.08), (0.3, 0.2, 0.0)),             # close, inside the fold's reach
])
@pytest.mark.slow
def test_crumpled_cloth_depth_equals_an_independent_ray_cast(eye, target):
    sim = _sim(14)
    x = _crumpled(sim)
    cam = Camera.looking_at(72, 54, 70.0, eye, target, near=0.02, far=3.0)
    depth, _ = cam.render(sim)
    ref = _reference_cast(cam, x, sim.mesh.faces)
    assert np.array_equal(np.isnan(depth), np.isnan(ref))
    assert np.isfinite(ref).sum() > 200
    np.testing.assert_allclose(depth[np.isfinite(ref)], ref[np.isfinite(ref)], atol=1e-5)


def test_points_back_projected_with_k_lie_on_the_mesh():
    sim = _sim(14)
    x = _crumpled(sim)
    cam = Camera.looking_at(80, 60, 60.0, (0.6, 0.4, 0.9), (0.0, 0.0, 0.0))
    depth, _ = cam.render(sim)
    pts = cam.points(depth)
    assert pts.dtype == np.float32 and pts.shape == (60, 80, 3)
    assert np.array_equal(np.isnan(pts[..., 2]), np.isnan(depth))
    # image_geometry's projectPixelTo3dRay scaled by the depth: K^-1 (u, v, 1) z
    K = cam.intrinsics
    v, u = np.nonzero(np.isfinite(depth))
    z = depth[v, u].astype(float)
    ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(z)], -1)
    np.testing.assert_allclose(pts[v, u], ray * z[:, None], rtol=1e-6, atol=1e-6)
    world = cam.position + (ray * z[:, None]) @ rotation_matrix(cam.orientation).T
    # every point within 1e-5 m of a triangle: near its plane, inside its edges
    faces = sim.mesh.faces
    a, b, c = x[faces[:, 0]], x[faces[:, 1]], x[faces[:, 2]]
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    on = np.zeros(len(world), bool)
    for f in range(len(faces)):
        dist = (world - a[f]) @ n[f]
        p = world - dist[:, None] * n[f]
        ok = np.abs(dist) <= 1e-5
        for e0, e1 in ((a[f], b[f]), (b[f], c[f]), (c[f], a[f])):
            ok &= (np.cross(e1 - e0, p - e0) @ n[f]) >= -1e-9
        on |= ok
    assert on.all(), f'{(~on).sum()} of {len(on)} points are off the mesh'


# ------------------------------------------------------------------ obstacles
def _alone(sim):
    """Move the cloth far out of every view of the obstacle tests."""
    x = sim.positions
    x[:, 2] += 100.0
    sim.set_positions(x)


def _sphere_t(o, d, c, r):
    oc = o - c
    b = (d * oc).sum(-1)
    a = (d * d).sum(-1)
    disc = b * b - a * ((oc * oc).sum() - r * r)
    t = (-b - np.sqrt(np.maximum(disc, 0))) / a
    return np.where(disc >= 0, t, np.nan)


def _local(cam, center, q):
    """The pixel rays in an obstacle's frame: (origin (3), directions (h, w, 3), d_z
    in the optical frame for depth)."""
    dw, dc = _world_rays(cam)
    R = rotation_matrix(q)
    return R.T @ (cam.position - center), dw @ R, dc[..., 2]


def _box_t(o, d, h):
    """The nearest hit of a ray on any of the six faces that lies within the face."""
    best = np.full(d.shape[:-1], np.inf)
    for k in range(3):
        for s in (-1.0, 1.0):
            with np.errstate(divide='ignore', invalid='ignore'):
                t = (s * h[k] - o[k]) / d[..., k]
            p = o + t[..., None] * d
            others = [j for j in range(3) if j != k]
            ok = (t > 0) & np.all(np.abs(p[..., others]) <= np.array(h)[others], -1)
            best = np.where(ok & (t < best), t, best)
    return np.where(np.isfinite(best), best, np.nan)


def _cylinder_t(o, d, r, l, caps=True):
    a = d[..., 0] ** 2 + d[..., 1] ** 2
    b = o[0] * d[..., 0] + o[1] * d[..., 1]
    c = o[0] ** 2 + o[1] ** 2 - r * r
    disc = b * b - a * c
    with np.errstate(invalid='ignore', divide='ignore'):
        t_side = (-b - np.sqrt(disc)) / a
    side_ok = (disc >= 0) & (np.abs(o[2] + t_side * d[..., 2]) <= l)
    best = np.where(side_ok, t_side, np.inf)
    for zc in (-l, l) if caps else ():
        with np.errstate(divide='ignore', invalid='ignore'):
            t = (zc - o[2]) / d[..., 2]
        p = o + t[..., None] * d
        ok = (t > 0) & (p[..., 0] ** 2 + p[..., 1] ** 2 <= r * r)
        best = np.where(ok & (t < best), t, best)
    return np.where(np.isfinite(best), best, np.nan)


@pytest.mark.parametrize('shape', ['sphere', 'box', 'cylinder', 'capsule'])
def test_shapes_render_at_their_closed_form_ray_intersections(shape):
    sim = _sim(4)
    _alone(sim)
    q = np.array([0.2, -0.3, 0.1, 0.9])
    q /= np.linalg.norm(q)
    c = np.array([0.1, -0.05, 0.2])
    if shape == 'sphere':
        sim.add_obstacle('sphere', center=c, radius=0.25)
    elif shape == 'box':
        sim.add_obstacle('box', center=c, half_extents=(0.3, 0.15, 0.1), orientation=q)
    else:
        sim.add_obstacle(shape, center=c, radius=0.12, half_length=0.2, orientation=q)
    cam = Camera.looking_at(96, 72, 55.0, c + (0.6, -0.5, 0.45), c)
    depth, rgb = cam.render(sim)
    o, d, dz = _local(cam, c, q if shape != 'sphere' else (0, 0, 0, 1))
    if shape == 'sphere':
        t = _sphere_t(o, d, np.zeros(3), 0.25)
    elif shape == 'box':
        t = _box_t(o, d, np.array([0.3, 0.15, 0.1]))
    elif shape == 'cylinder':
        t = _cylinder_t(o, d, 0.12, 0.2)
    else:
        t = _cylinder_t(o, d, 0.12, 0.2, caps=False)           # the side, then the ends
        for zc in (-0.2, 0.2):
            t = np.fmin(t, _sphere_t(o, d, np.array([0.0, 0.0, zc]), 0.12))
    ref = t * dz
    assert np.isfinite(ref).sum() > 300
    assert np.array_equal(np.isnan(depth), np.isnan(ref))
    np.testing.assert_allclose(depth[np.isfinite(ref)], ref[np.isfinite(ref)], atol=5e-4)
    grey = rgb[np.isfinite(ref)]
    assert np.all(grey[:, 0] == grey[:, 1]) and np.all(grey[:, 1] == grey[:, 2])


def test_a_plane_and_a_mesh_obstacle_and_the_nearest_surface_wins():
    import trimesh
    sim = _sim(8, side=0.6)
    sim.add_obstacle('plane', point=(0, 0, -0.5), normal=(0, 0, 1))
    box = trimesh.creation.box(extents=(0.4, 0.4, 0.2))
    sim.add_obstacle('mesh', vertices=box.vertices, faces=box.faces, center=(0, 0, -0.3),
                     spacing=0.02)
    cam = Camera(80, 60, 60.0, (0.0, 0.0, 1.0), DOWN)
    depth, rgb = cam.render(sim)
    # the cloth (z = 0) over the box's top (z = -0.2) over the ground (z = -0.5)
    assert depth[30, 40] == pytest.approx(1.0, abs=1e-6)
    x = sim.positions
    x[:, 2] += 5.0                               # the cloth behind the camera
    sim.set_positions(x)
    depth, rgb = cam.render(sim)
    assert depth[30, 40] == pytest.approx(1.2, abs=1e-6)
    assert depth[2, 2] == pytest.approx(1.5, abs=1e-6)
    assert rgb[30, 40, 0] == rgb[30, 40, 1] == rgb[30, 40, 2]
    assert rgb[2, 2, 0] > rgb[30, 40, 0]         # planes a lighter grey


def test_colours_are_the_vertices_and_render_returns_fresh_arrays():
    sim = _sim(6)
    cam = Camera(40, 30, 40.0, (0, 0, 1.0), DOWN)
    red = np.zeros((sim.n_vertices, 4))
    red[:, 0] = red[:, 3] = 1.0
    d1, rgb = cam.render(sim, colors=red)
    assert rgb[15, 20, 0] > 240 and rgb[15, 20, 1] == 0 and rgb[15, 20, 2] == 0
    d2, _ = cam.render(sim)
    d2[:] = 0
    assert np.isfinite(d1).any() and not np.shares_memory(d1, d2)
    with pytest.raises(ValueError, match='colors must be'):
        cam.render(sim, colors=np.zeros((3, 3)))


def test_near_and_far_clip_and_set_pose_moves_the_view():
    sim = _sim(6)
    cam = Camera(40, 30, 40.0, (0, 0, 1.0), DOWN, near=0.01, far=0.9)
    depth, _ = cam.render(sim)
    assert np.isnan(depth).all()
    cam.set_pose((0, 0, 0.5), DOWN)
    depth, _ = cam.render(sim)
    assert depth[15, 20] == pytest.approx(0.5, abs=1e-9)
    with pytest.raises(ValueError, match='unit quaternion'):
        cam.set_pose((0, 0, 0.5), (0, 0, 0, 0))


def test_snapshot_writes_a_params_files_camera_or_refuses_in_one_line(tmp_path, capsys):
    from pathlib import Path
    from cosserat_ros.tools import snapshot
    table = str(Path(__file__).resolve().parents[1] / 'config' / 'table.yaml')
    out = tmp_path / 'side.png'
    assert snapshot.main([table, '--camera', 'side', '--seconds', '0', '-o', str(out),
                          '--npz', str(tmp_path / 'side.npz')]) == 0
    assert out.stat().st_size > 10_000
    data = np.load(tmp_path / 'side.npz')
    assert data['depth'].shape == (480, 640) and data['rgb'].shape == (480, 640, 3)
    assert np.isfinite(data['depth']).mean() > 0.3
    capsys.readouterr()
    assert snapshot.main([table, '--camera', 'top', '-o', str(tmp_path / 'x.png')]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and "no camera 'top'" in err
