"""The contact's inside test and penetration depth (physics/indenter_query.py ``penetration``) against an exact
reference, on every indenter of the library: points near their vertices and edges (where a sign taken from the wrong
face would be wrong), points at contact depths (1e-4 to 0.05 mm) on either side of their faces, and points spread
over their bounding boxes. (Warp's pseudo-normal sign, tried in commit f71967c, passes these points; a denser
sampling in review, a throwaway script not kept, found it wrong at a few points deep inside the coin and the pocket
block. The inside test at an edge or a vertex is now the closest feature's own angle-weighted pseudo-normal, the
winding number only where the features that the closest point's weights allow disagree: 0 points wrong with ``python
tests/test_physics_contact_query.py 0 15`` and ``16 47`` on the 2-core CPU.)

Reference (numpy, exact for a closed mesh): inside where the generalised winding number (the sum of the triangles'
solid angles, Van Oosterom & Strackee 1983, over 4 pi) is 1, and the depth is the distance to the closest point of
any triangle (Ericson, Real-Time Collision Detection, 5.1.5). The inside test must be exact; the depth is compared
within 0.01 mm, half the penetration tolerance (0.02 mm): Warp's closest-point query leaves out nearly degenerate
triangles, and near the thin faces of the brick and the cone the depth to the plane of the face it returns was up to
0.0066 and 0.0032 mm off, the inside test right everywhere (``python tests/test_physics_contact_query.py 0 15``: the
points of seeds 0-15, 2-core CPU; the same depths with the winding-number query before, commit 31c75b7). Not fixed:
found here, and small against the tolerance that the solver enforces."""

from pathlib import Path

import numpy as np
import pytest
import trimesh
import warp as wp

from transtac_sim.physics import ElasticMaterial, QuasiStaticSolver, RigidIndenter, indenter_query
from transtac_sim.physics.box_mesh import box_tet_mesh

INDENTERS = Path(__file__).resolve().parents[1] / "scenes" / "indenters"
MESHES = sorted(p.stem for p in INDENTERS.glob("*.stl"))
DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() else [])


@wp.kernel
def _penetrations(ind: indenter_query.Indenters, points: wp.array(dtype=wp.vec3d), depth: wp.array(dtype=wp.float64)):
    i = wp.tid()
    g, n = indenter_query.penetration(ind, 0, points[i])
    depth[i] = g


def _winding_numbers(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    a, b, c = (triangles[None, :, k, :] - points[:, None, :] for k in range(3))
    la, lb, lc = (np.linalg.norm(v, axis=2) for v in (a, b, c))
    numerator = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
    denominator = la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", b, c) * la \
        + np.einsum("pfi,pfi->pf", c, a) * lb
    return np.sum(2.0 * np.arctan2(numerator, denominator), axis=1) / (4.0 * np.pi)


def _closest_distances(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Distance from each point to each triangle (Ericson 5.1.5, vectorised over points x triangles), minimised."""
    p = points[:, None, :]
    a, b, c = (triangles[None, :, k, :] for k in range(3))
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (np.einsum("pfi,pfi->pf", e, ap) for e in (np.broadcast_to(ab, ap.shape), np.broadcast_to(ac, ap.shape)))
    bp, cp = p - b, p - c
    d3, d4 = np.einsum("pfi,pfi->pf", np.broadcast_to(ab, bp.shape), bp), np.einsum("pfi,pfi->pf", np.broadcast_to(ac, bp.shape), bp)
    d5, d6 = np.einsum("pfi,pfi->pf", np.broadcast_to(ab, cp.shape), cp), np.einsum("pfi,pfi->pf", np.broadcast_to(ac, cp.shape), cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v, w = vb * denom, vc * denom
        closest = a + ab * v[..., None] + ac * w[..., None]  # inside the face
        regions = [  # (condition, closest point), the first that holds wins: vertices, then edges
            ((d1 <= 0) & (d2 <= 0), np.broadcast_to(a, closest.shape)),
            ((d3 >= 0) & (d4 <= d3), np.broadcast_to(b, closest.shape)),
            ((d6 >= 0) & (d5 <= d6), np.broadcast_to(c, closest.shape)),
            ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * (d1 / (d1 - d3))[..., None]),
            ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * (d2 / (d2 - d6))[..., None]),
            ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
             b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[..., None]),
        ]
    for condition, point in reversed(regions):
        closest = np.where(condition[..., None], point, closest)
    return np.min(np.linalg.norm(p - closest, axis=2), axis=1)


def _query_points(mesh: trimesh.Trimesh, rng: np.random.Generator) -> np.ndarray:
    """Points within 0.02-0.5 mm of the vertices and edge midpoints, 1e-4 to 0.05 mm from faces on either side, and
    spread over the bounding box."""
    edges = mesh.vertices[mesh.edges_unique]
    features = np.concatenate([mesh.vertices, edges.mean(axis=1)])
    features = features[rng.integers(len(features), size=300)]
    offsets = rng.standard_normal(features.shape)
    offsets *= (rng.uniform(0.02, 0.5, len(features)) / np.linalg.norm(offsets, axis=1))[:, None]
    faces = rng.integers(len(mesh.faces), size=300)
    on_faces = np.einsum("fk,fki->fi", rng.dirichlet([1.0, 1.0, 1.0], size=300), mesh.vertices[mesh.faces[faces]])
    depths = rng.choice([-1.0, 1.0], 300) * 10.0 ** rng.uniform(-4.0, -1.3, 300)
    lo, hi = mesh.bounds
    return np.concatenate([features + offsets, on_faces - mesh.face_normals[faces] * depths[:, None],
                           rng.uniform(lo - 0.5, hi + 0.5, (600, 3))])


def _compare(name: str, seed: int, device: str = "cpu") -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For the library indenter ``name`` and the query points of ``seed``: (indenter_query.py's depth on ``device``,
    exact inside, exact distance, points off the surface), in mm."""
    mesh = trimesh.load(INDENTERS / f"{name}.stl")
    indenter = RigidIndenter.from_trimesh(name, mesh)
    V, T = box_tet_mesh(np.linspace(0, 1, 2), np.linspace(0, 1, 2), np.linspace(0, 1, 2))
    solver = QuasiStaticSolver(V, T, ElasticMaterial(0.5, 0.45), [indenter], device=device)
    ind = solver._indenter_struct([np.eye(4)], [np.eye(4)])
    points = _query_points(mesh, np.random.default_rng(seed))
    depth = wp.zeros(len(points), dtype=wp.float64, device=device)
    wp.launch(_penetrations, dim=len(points), inputs=[ind, wp.array(points, dtype=wp.vec3d, device=device), depth],
              device=device)
    triangles = mesh.vertices[mesh.faces]
    inside = np.abs(_winding_numbers(points, triangles)) > 0.5
    distance = _closest_distances(points, triangles)
    return depth.numpy(), inside, distance, distance > 5e-5  # off the surface, where either answer is right


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name", MESHES)
def test_penetration_matches_the_exact_inside_test_and_distance(name: str, device: str):
    g, inside, distance, clear = _compare(name, 5, device)
    assert clear.sum() > 1000 and inside[clear].sum() > 200 and (~inside[clear]).sum() > 200
    assert np.all(g[clear & ~inside] == 0.0)
    np.testing.assert_allclose(g[clear & inside], distance[clear & inside], rtol=0, atol=1e-2)


@wp.kernel
def _penetrations_and_normals(ind: indenter_query.Indenters, points: wp.array(dtype=wp.vec3d),
                              depth: wp.array(dtype=wp.float64), normal: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    g, n = indenter_query.penetration(ind, 0, points[i])
    depth[i] = g
    normal[i] = n


@pytest.mark.parametrize("device", DEVICES)
def test_penetration_at_an_edge_inside_a_flat_face_is_exact(device: str):
    """A 40 x 40 mm plate's bottom face is two triangles that meet along its diagonal x + y = 0. Under it, points within
    1e-5 mm of the diagonal have their closest point on that edge, where the depth and normal were taken from Warp's
    float32 closest point: up to 8.6e-8 mm and 0.033 off on these points (depths 1e-4 to 1e-2 mm; commit 0623410, a
throwaway check),
    enough noise in the contact energy that Newton stalled on a plate pressed onto a block
    (``test_plate_wider_than_the_gel_presses_it_in_few_newton_iterations``). An edge between coplanar faces now takes
    the face's plane (``_on_flat_edge``): exact to round-off."""
    plate = RigidIndenter.from_trimesh("plate", trimesh.creation.box(extents=(40.0, 40.0, 2.0)))
    V, T = box_tet_mesh(np.linspace(0, 1, 2), np.linspace(0, 1, 2), np.linspace(0, 1, 2))
    solver = QuasiStaticSolver(V, T, ElasticMaterial(0.5, 0.45), [plate], device=device)
    ind = solver._indenter_struct([np.eye(4)], [np.eye(4)])
    rng = np.random.default_rng(0)
    along = rng.uniform(-3.0, 3.0, 200)
    across = rng.uniform(-1e-5, 1e-5, 200)  # within 1e-5 mm of the diagonal: on the edge for the query's tolerance
    depths = 10.0 ** rng.uniform(-4.0, -2.0, 200)
    points = np.stack([along + across, -along + across, -1.0 + depths], axis=1)
    depth = wp.zeros(len(points), dtype=wp.float64, device=device)
    normal = wp.zeros(len(points), dtype=wp.vec3d, device=device)
    wp.launch(_penetrations_and_normals, dim=len(points), device=device,
              inputs=[ind, wp.array(points, dtype=wp.vec3d, device=device), depth, normal])
    np.testing.assert_allclose(depth.numpy(), depths, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(normal.numpy(), np.tile([0.0, 0.0, -1.0], (len(points), 1)), atol=1e-9)


@wp.kernel
def _closest_points(p: wp.array(dtype=wp.vec3d), tri: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec3d)):
    i = wp.tid()
    out[i] = indenter_query._closest_on_triangle(p[i], tri[3 * i], tri[3 * i + 1], tri[3 * i + 2])


def _closest_by_candidates(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """The closest point of each triangle another way than Ericson's regions: the nearest of the projection onto the
    plane (where it falls inside), the projections onto the three edges (clamped to them) and the three corners."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    candidates = [a, b, c]
    for s, e in ((a, b), (b, c), (c, a)):
        t = np.clip(np.einsum("ij,ij->i", p - s, e - s) / np.einsum("ij,ij->i", e - s, e - s), 0.0, 1.0)
        candidates.append(s + (e - s) * t[:, None])
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    projected = p - np.einsum("ij,ij->i", p - a, n)[:, None] * n
    inside = np.ones(len(p), dtype=bool)
    for s, e in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(e - s, projected - s), n) >= 0.0
    candidates.append(np.where(inside[:, None], projected, a))
    stacked = np.stack(candidates, axis=1)
    best = np.argmin(np.linalg.norm(stacked - p[:, None], axis=2), axis=1)
    return stacked[np.arange(len(p)), best]


def test_closest_point_on_a_triangle_in_every_region_and_on_a_degenerate_one():
    """``_closest_on_triangle`` (Ericson's seven regions) against the nearest of the candidate points, for points all
    around random triangles (every region is hit); a triangle with two equal corners or all three gives a finite point
    of it (a closed indenter mesh may keep such a face: RigidIndenter does not drop them)."""
    rng = np.random.default_rng(1)
    tri = rng.uniform(-1.0, 1.0, (4000, 3, 3))
    p = rng.uniform(-2.0, 2.0, (4000, 3))
    out = wp.zeros(len(p), dtype=wp.vec3d)
    wp.launch(_closest_points, dim=len(p),
              inputs=[wp.array(p, dtype=wp.vec3d), wp.array(tri.reshape(-1, 3), dtype=wp.vec3d), out])
    np.testing.assert_allclose(out.numpy(), _closest_by_candidates(p, tri), rtol=0, atol=1e-9)
    degenerate = np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], [[0.5, 0.5, 0.5]] * 3])
    q = np.array([[0.3, 1.0, 0.0], [0.0, 0.0, 0.0]])
    out = wp.zeros(2, dtype=wp.vec3d)
    wp.launch(_closest_points, dim=2,
              inputs=[wp.array(q, dtype=wp.vec3d), wp.array(degenerate.reshape(-1, 3), dtype=wp.vec3d), out])
    got = out.numpy()  # a point of each degenerate triangle (not always its closest: Ericson's regions assume area)
    assert np.isfinite(got).all() and 0.0 <= got[0, 0] <= 1.0 and np.allclose(got[0, 1:], 0.0)
    np.testing.assert_allclose(got[1], [0.5, 0.5, 0.5], atol=1e-12)


def test_feature_normals_of_a_cube_point_along_its_corners_and_edges():
    """``RigidIndenter.feature_normals`` on a triangulated unit cube: each face's normal, each corner's angle-weighted
    pseudo-normal along the corner's diagonal (its three squares weigh the same whichever way they are split), and each
    edge's the mean of its two faces' normals (a cube edge: the diagonal of the two axes; a square's diagonal: the
    square's normal)."""
    mesh = trimesh.creation.box((1.0, 1.0, 1.0))
    normals = RigidIndenter.from_trimesh("cube", mesh).feature_normals()
    corners = mesh.vertices[mesh.faces]  # (faces, 3, 3), at +-0.5

    def along(v):  # the unit vector of v's components at +-0.5, the others 0
        d = np.where(np.isclose(np.abs(v), 0.5), np.sign(v), 0.0)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    np.testing.assert_allclose(normals[:, 0], mesh.face_normals, atol=1e-12)
    np.testing.assert_allclose(normals[:, 1:4], along(corners), atol=1e-12)
    midpoints = 0.5 * (corners[:, [1, 2, 0]] + corners[:, [2, 0, 1]])  # the edge opposite each corner
    np.testing.assert_allclose(normals[:, 4:7], along(midpoints), atol=1e-12)
    assert np.sum(np.isclose(np.abs(midpoints), 0.5).sum(axis=2) == 2) == 24  # each of the 12 cube edges, twice


if __name__ == "__main__":  # the sweep behind the docstring's figures: python tests/test_physics_contact_query.py 0 15
    import sys

    first, last = (int(a) for a in sys.argv[1:3])
    for name in MESHES:
        wrong, error = 0, 0.0
        for seed in range(first, last + 1):
            g, inside, distance, clear = _compare(name, seed)
            wrong += int(np.sum(clear & (inside != (g > 0.0))))
            error = max(error, float(np.max(np.abs(g - distance)[clear & inside])))
        print(f"{name}: seeds {first}-{last}, inside test wrong at {wrong} points, largest depth error {error:.2g} mm")
