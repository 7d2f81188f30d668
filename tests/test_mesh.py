"""Mesh geometry, shape functions and level transfer against hand-known values."""

from __future__ import annotations

import numpy as np

from chunkdic.mesh import Mesh, carry_field, level_to_level, shape_table, transfer


def test_shape_table_values_by_hand():
    N = shape_table(2)  # local coordinates 1/4 and 3/4
    assert N.shape == (2, 2, 2, 8)
    assert np.isclose(N[0, 0, 0, 0], 0.75**3)
    assert np.isclose(N[0, 0, 0, 7], 0.25**3)
    assert np.isclose(N[1, 0, 1, 5], 0.75 * 0.75 * 0.75)  # a=5: dz=1, dy=0, dx=1
    np.testing.assert_allclose(N.sum(-1), 1.0)


def test_nodes_sit_on_element_faces():
    m = Mesh((10, 20, 30), 8, (2, 3, 4))
    c = m.node_coords()
    assert c.shape == (3, 3, 4, 5)
    assert c[0, 0, 0, 0] == 9.5 and c[0, -1, 0, 0] == 25.5
    assert [(r.start, r.stop) for r in m.roi] == [(10, 26), (20, 44), (30, 62)]
    assert m.n_voxels == 24 * 8**3


def test_blocks_tile_the_mesh_exactly():
    m = Mesh((0, 0, 0), 4, (5, 3, 2))
    for size in (1, 2, 4, 9):
        blocks = m.blocks(size)
        cover = np.zeros(m.shape, int)
        for b in blocks:
            cover[tuple(slice(a, c) for a, c in b.elements)] += 1
        assert (cover == 1).all()


def test_evaluate_reproduces_affine_fields_inside_and_outside():
    m = Mesh((3, 4, 5), 6, (3, 2, 2))
    A = np.array([[0.01, -0.02, 0.03], [0.0, 0.015, 0.0], [-0.01, 0.0, 0.02]])
    c = np.array([0.5, -1.0, 2.0])
    nodes = m.node_coords()
    u = np.einsum("ij,j...->i...", A, nodes) + c[:, None, None, None]
    pts = np.random.default_rng(0).uniform(-5, 30, size=(3, 50))  # also outside the mesh
    np.testing.assert_allclose(m.evaluate(u, pts), A @ pts + c[:, None], atol=1e-12)


def test_level_offsets():
    # level-1 voxel 0 is centred at level-0 coordinate 0.5; level-2 voxel 1 at 5.5
    assert level_to_level(np.array(0.0), 1, 0) == 0.5
    assert level_to_level(np.array(1.0), 2, 0) == 5.5
    assert level_to_level(np.array(5.5), 0, 2) == 1.0


def test_transfer_of_an_affine_field_is_exact():
    """u0(X0) = A X0 + c in level-0 voxels; on level s it is u0 / 2^s at level-s positions."""
    A = np.array([[-0.01, 0.0, 0.005], [0.0, 0.002, 0.0], [0.0, 0.0, 0.003]])
    c = np.array([1.5, -0.5, 2.0])
    coarse = Mesh((2, 2, 2), 8, (3, 3, 3))
    fine = Mesh((5, 5, 5), 8, (6, 6, 6))

    def field_at_level(mesh, s):
        p = mesh.node_coords()
        x0 = 2**s * p + (2**s - 1) / 2
        return (np.einsum("ij,j...->i...", A, x0) + c[:, None, None, None]) / 2**s

    u1 = field_at_level(coarse, 1)
    np.testing.assert_allclose(transfer(u1, coarse, 1, fine, 0), field_at_level(fine, 0), atol=1e-12)


def test_evaluate_grid_equals_pointwise_evaluation():
    """The separable grid evaluation (fields export) equals Mesh.evaluate on the meshgrid,
    inside the mesh and in its linear extension outside."""
    rng = np.random.default_rng(0)
    mesh = Mesh((3, 2, 5), 4, (2, 3, 2))
    u = rng.normal(size=(3, *mesh.nodes_shape))
    axes = [np.linspace(o - 3.0, o + n * 4 + 2.0, 11) for o, n in zip(mesh.origin, mesh.shape)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"))
    assert np.allclose(mesh.evaluate_grid(u, axes), mesh.evaluate(u, pts), atol=1e-12)


def test_carry_field_clamped_extends_one_element_then_holds():
    """``clamp=True`` (start fields, composed increments): an affine field stays exact up to
    one element beyond the outer nodes and keeps the value at that limit further out;
    unclamped it keeps growing (the level transfer's linear extension)."""
    A = np.array([[0.02, 0.0, 0.0], [0.0, -0.01, 0.0], [0.0, 0.0, 0.03]])
    mesh = Mesh((4, 4, 4), 8, (2, 2, 2))  # nodes at 3.5, 11.5, 19.5 on every axis
    u = np.einsum("ij,j...->i...", A, mesh.node_coords())
    pts = np.array([[19.5 + 8, 3.5 - 8, 11.0], [19.5 + 30, 3.5 - 30, 11.0], [11.0, 11.0, 11.0]]).T  # (3, 3)
    limit = np.array([[27.5, -4.5, 11.0], [27.5, -4.5, 11.0], [11.0, 11.0, 11.0]]).T
    np.testing.assert_allclose(carry_field(u, mesh, 0, pts, 0, clamp=True), A @ limit, atol=1e-12)
    np.testing.assert_allclose(carry_field(u, mesh, 0, pts, 0), A @ pts, atol=1e-12)
    # between levels: positions and values of level 1 (X1 = (X0 - 0.5) / 2, u1 = u0 / 2)
    p1 = (pts - 0.5) / 2
    np.testing.assert_allclose(carry_field(u, mesh, 0, p1, 1, clamp=True), A @ limit / 2, atol=1e-12)
