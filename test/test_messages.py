"""The numpy CDR writer against rclpy's own (de)serialiser."""

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from geometry_msgs.msg import Point
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from cosserat_ros.mesh import grid_mesh
from cosserat_ros.ros.conversions import colormap, mesh_marker_array


def slow_marker_array(x, faces, col, stamp_ns, frame, edges, pins, pin_size=0.02):
    """The obvious construction: one Point and one ColorRGBA object per corner."""
    out = MarkerArray()

    def marker(mid, mtype, scale, color, pts, cols=None):
        m = Marker()
        m.header.frame_id = frame
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(stamp_ns, 10 ** 9)
        m.ns, m.id, m.type, m.action = 'cloth', mid, mtype, Marker.ADD
        m.pose.orientation.w = 1.0
        m.scale.x = m.scale.y = m.scale.z = scale
        m.color = ColorRGBA(r=color[0], g=color[1], b=color[2], a=color[3])
        m.points = [Point(x=float(a), y=float(b), z=float(c)) for a, b, c in pts]
        if cols is not None:
            m.colors = [ColorRGBA(r=float(r), g=float(g), b=float(b), a=float(a))
                        for r, g, b, a in cols]
        return m
    out.markers.append(marker(0, Marker.TRIANGLE_LIST, 1.0, (1.0, 1.0, 1.0, 1.0),
                              x[faces.ravel()], col[faces.ravel()]))
    out.markers.append(marker(1, Marker.LINE_LIST, 0.002, (0.1, 0.1, 0.1, 1.0),
                              x[edges.ravel()]))
    out.markers.append(marker(2, Marker.SPHERE_LIST, pin_size, (0.9, 0.2, 0.1, 1.0), x[pins]))
    return out


def decode_vertices(marker, faces, n):
    """Per-vertex values back from a TRIANGLE_LIST (one entry per triangle corner)."""
    pts = np.array([[p.x, p.y, p.z] for p in marker.points])
    cols = np.array([[c.r, c.g, c.b, c.a] for c in marker.colors], dtype=np.float32)
    first = np.unique(faces.ravel(), return_index=True)[1]
    return pts[first], cols[first], pts.reshape(-1, 3, 3)


@pytest.mark.parametrize('pattern', ['regular', 'alternating', 'irregular'])
def test_marker_array_decodes_to_the_simulator_arrays(pattern):
    mesh = grid_mesh(7, 5, pattern=pattern, seed=3)
    rng = np.random.default_rng(0)
    x = mesh.vertices + 0.01 * rng.standard_normal(mesh.vertices.shape)
    col = colormap(rng.random(mesh.n_vertices), 0.0, 1.0)
    data = mesh_marker_array(x, mesh.faces, col, 12_345_678_901, 'cloth_frame',
                             edges=mesh.edges, pinned=np.array([0, 7]))
    msg = deserialize_message(data, MarkerArray)
    slow = slow_marker_array(x, mesh.faces, col, 12_345_678_901, 'cloth_frame', mesh.edges,
                             np.array([0, 7]))
    wire = serialize_message(slow)                       # float32 fields rounded as on the wire
    assert msg == deserialize_message(wire, MarkerArray)  # field by field, every value
    assert len(wire) == len(data)                        # same layout (padding bytes differ)
    tri, wire, pins = msg.markers
    assert tri.type == Marker.TRIANGLE_LIST and wire.type == Marker.LINE_LIST
    assert pins.type == Marker.SPHERE_LIST
    assert tri.header.frame_id == 'cloth_frame'
    assert (tri.header.stamp.sec, tri.header.stamp.nanosec) == (12, 345_678_901)
    assert tri.color.a > 0 and (tri.scale.x, tri.scale.y, tri.scale.z) == (1.0, 1.0, 1.0)
    pos, cols, corners = decode_vertices(tri, mesh.faces, mesh.n_vertices)
    assert np.array_equal(pos, x)
    assert np.array_equal(cols, col)
    assert np.array_equal(corners, x[mesh.faces])      # the faces, corner by corner
    assert len(wire.points) == 2 * len(mesh.edges)
    assert np.array_equal([[p.x, p.y, p.z] for p in pins.points], x[[0, 7]])


def test_marker_array_without_optional_markers():
    mesh = grid_mesh(2, 2)
    col = colormap(np.zeros(mesh.n_vertices), 0, 1)
    msg = deserialize_message(mesh_marker_array(mesh.vertices, mesh.faces, col, 0, 'w'),
                              MarkerArray)
    assert len(msg.markers) == 1


def test_handles_are_their_own_sphere_list():
    mesh = grid_mesh(3, 3)
    col = colormap(np.zeros(mesh.n_vertices), 0, 1)
    handles = np.array([[0.1, 0.2, 0.3], [-0.4, 0.5, 0.6]])
    msg = deserialize_message(mesh_marker_array(mesh.vertices, mesh.faces, col, 0, 'w',
                                                pinned=np.array([0, 3]), pin_size=0.01,
                                                handles=handles), MarkerArray)
    assert [m.id for m in msg.markers] == [0, 2, 3]
    m = msg.markers[2]
    assert m.type == Marker.SPHERE_LIST and m.scale.x == pytest.approx(0.03)
    np.testing.assert_array_equal([[p.x, p.y, p.z] for p in m.points], handles)
    assert m.header.frame_id == 'w' and m.ns == 'cloth'


def test_markers_the_last_message_drew_are_deleted():
    """A DELETE marker (namespace and id, no points) for each id in ``delete``, after the
    drawn ones; optional_markers says which ids a message draws."""
    from cosserat_ros.ros.conversions import optional_markers
    mesh = grid_mesh(3, 3)
    col = colormap(np.zeros(mesh.n_vertices), 0, 1)
    before = optional_markers(mesh.edges, np.array([0, 3]), np.zeros((1, 3)))
    now = optional_markers(None, np.array([], int), None)
    assert before == {1, 2, 3} and now == frozenset()
    assert optional_markers(mesh.edges, None, np.zeros((0, 3))) == {1}
    msg = deserialize_message(mesh_marker_array(mesh.vertices, mesh.faces, col, 0, 'w',
                                                delete=sorted(before - now)), MarkerArray)
    assert [m.id for m in msg.markers] == [0, 1, 2, 3]
    assert msg.markers[0].action == Marker.ADD
    for m in msg.markers[1:]:
        assert m.action == Marker.DELETE and m.ns == 'cloth' and not m.points


def test_colormap_range_and_degenerate_span():
    c = colormap(np.array([-1.0, 0.0, 0.5, 1.0, 2.0, np.nan]), 0.0, 1.0, alpha=0.5)
    assert c.dtype == np.float32 and c.shape == (6, 4)
    assert np.all((c >= 0) & (c <= 1)) and np.all(c[:, 3] == 0.5)
    assert np.array_equal(c[0], c[1]) and np.array_equal(c[3], c[4])
    assert not np.array_equal(c[1], c[3])
    assert np.all(np.isfinite(colormap(np.ones(3), 1.0, 1.0)))
    # piecewise linear through the 8 control points, evenly spaced over [vmin, vmax]
    stops = colormap(np.arange(8) / 7.0 * 2.0 - 1.0, -1.0, 1.0)[:, :3]
    mid = colormap((np.arange(7) + 0.5) / 7.0, 0.0, 1.0)[:, :3]
    assert np.allclose(mid, 0.5 * (stops[:-1] + stops[1:]), atol=1e-6)
    assert np.allclose(stops[[0, -1]], [[0.267004, 0.004874, 0.329415],
                                        [0.993248, 0.906157, 0.143936]], atol=1e-6)


def test_building_a_large_mesh_message_is_cheap():
    """No per-point Python work: the corners go through numpy, so building the message
    makes as many Python and C calls for an 80 x 80 mesh (38,400 corners) as for a 10 x 10
    one (counted with a profile hook, not timed: a shared machine's clock says nothing),
    where the one-object-per-point builder of this file makes more with every point."""
    import sys

    def calls(build, n):
        mesh = grid_mesh(n, n)
        col = colormap(mesh.vertices[:, 0], -0.5, 0.5)
        count = [0]

        def hook(frame, event, arg):
            if event in ('call', 'c_call'):
                count[0] += 1
        sys.setprofile(hook)
        try:
            data = build(mesh.vertices, mesh.faces, col, 0, 'w', mesh.edges, np.arange(9))
        finally:
            sys.setprofile(None)
        return count[0], data

    def fast(x, faces, col, stamp, frame, edges, pins):
        return mesh_marker_array(x, faces, col, stamp, frame, edges=edges, pinned=pins)
    calls(fast, 4), calls(slow_marker_array, 4)         # first calls' one-time set-up
    (small, _), (large, data) = calls(fast, 10), calls(fast, 80)
    assert len(data) > 38400 * 40
    assert large == small, (small, large)
    slow = calls(slow_marker_array, 4)[0], calls(slow_marker_array, 8)[0]
    assert slow[1] > slow[0] + 3 * 2 * (64 - 16) * 3, slow      # it sees per-point work


def test_point_cloud_and_shape_mesh_are_what_rclpy_serialises():
    from geometry_msgs.msg import Point
    from sensor_msgs.msg import PointCloud2, PointField
    from shape_msgs.msg import Mesh, MeshTriangle
    from cosserat_ros.ros.conversions import point_cloud, POINT_FIELDS, shape_mesh
    m = grid_mesh(3, 2)
    rng = np.random.default_rng(0)
    x = m.vertices + 0.01 * rng.standard_normal(m.vertices.shape)
    v = rng.standard_normal(x.shape)
    wire = point_cloud(x, v, 3_250_000_000, 'world')
    msg = deserialize_message(wire, PointCloud2)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (3, 250_000_000)
    assert msg.height == 1 and msg.width == m.n_vertices and msg.point_step == 24
    assert [f.name for f in msg.fields] == list(POINT_FIELDS)
    assert all(f.datatype == PointField.FLOAT32 and f.count == 1 for f in msg.fields)
    data = np.frombuffer(bytes(msg.data), dtype='<f4').reshape(-1, 6)
    np.testing.assert_array_equal(data[:, :3], x.astype(np.float32))
    np.testing.assert_array_equal(data[:, 3:], v.astype(np.float32))
    assert msg.is_dense and not msg.is_bigendian
    assert len(serialize_message(msg)) == len(wire)
    wire = shape_mesh(x, m.faces)
    mesh = deserialize_message(wire, Mesh)
    ref = Mesh(triangles=[MeshTriangle(vertex_indices=[int(i) for i in f]) for f in m.faces],
               vertices=[Point(x=float(a), y=float(b), z=float(c)) for a, b, c in x])
    assert serialize_message(ref) == wire
    assert [list(t.vertex_indices) for t in mesh.triangles] == m.faces.tolist()
