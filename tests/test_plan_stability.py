"""Planner stability: the proxy perturbation and the view shift, on constructed inputs."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from experiments import plan_stability


def test_perturbation_moves_vertices_along_their_normals_by_sigma():
    plane = trimesh.creation.box(extents=(40.0, 40.0, 1.0)).subdivide().subdivide().subdivide().subdivide()
    moved = plan_stability.perturb_proxy(plane, 0.005, seed=1)
    offset = moved.vertices - plane.vertices
    along = np.einsum("ij,ij->i", offset, plane.vertex_normals)
    # All motion is along the normal; its spread is sigma (5 mm) within sampling error.
    np.testing.assert_allclose(np.linalg.norm(offset, axis=1), np.abs(along), atol=1e-12)
    assert len(along) > 1000
    assert np.std(along) == pytest.approx(0.005, rel=0.1)
    np.testing.assert_array_equal(moved.faces, plane.faces)
    # Same seed, same copy; sigma 0 leaves the proxy where it was.
    np.testing.assert_array_equal(plan_stability.perturb_proxy(plane, 0.005, seed=1).vertices, moved.vertices)
    np.testing.assert_array_equal(plan_stability.perturb_proxy(plane, 0.0, seed=1).vertices, plane.vertices)
    with pytest.raises(ValueError, match="sigma-mm"):
        plan_stability.perturb_proxy(plane, -0.001, seed=1)


def test_view_shift_is_the_distance_to_the_nearest_reference_view():
    reference = np.array([[0.0, 0.0, 10.0, 0.0, -90.0], [10.0, 0.0, 10.0, 0.0, -90.0]])
    views = np.array([[0.0, 3.0, 14.0, 45.0, -45.0], [9.0, 0.0, 10.0, 0.0, -90.0]])
    np.testing.assert_allclose(plan_stability.view_shift_m(views, reference), [5.0, 1.0])


def test_a_missing_proxy_is_one_clear_line(tmp_path, capsys):
    code = plan_stability.main(["--proxy", str(tmp_path / "none.ply"), "--out", str(tmp_path / "out")])
    assert code == 2
    assert "proxy mesh not found" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
