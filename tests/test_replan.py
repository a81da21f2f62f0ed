"""experiments.replan: which fields of two plan records differ, and the cell a record names."""

import numpy as np
import pytest

from experiments.replan import (
    Difference,
    cell_overrides,
    compare_plans,
    differences_line,
    main,
    proxy_is_records,
    same_value,
    views_line,
)

RECORD = {
    "planner": "smith",
    "n_viewpoints": 189,
    "flight_length_m": 1161.462732611519,
    "kinds": {"nadir": 63, "oblique": 126},
    "timings_s": {"optimise": 113.9},
    "objective_per_sweep": [12.41126179173574, 0.5, 0.013701387131447067],
    "optimisation": {"rounds": 6829, "restarts": 1046},
    "rays_cast": 30492388,
    "predicted_coverage": {"walls": 61.0},
}


def replanned(**changes) -> dict:
    plan = {k: v for k, v in RECORD.items() if k != "predicted_coverage"}  # run.py adds it, not replan
    return plan | changes


def test_same_plan_with_other_timings_and_rays_is_equal():
    assert compare_plans(RECORD, replanned(timings_s={"optimise": 64.0}, rays_cast=30492400)) == []


def test_floats_within_1e_9_relative_are_equal_and_beyond_are_not():
    near = replanned(flight_length_m=1161.462732611519 * (1 + 5e-10))
    far = replanned(flight_length_m=1161.462732611519 * (1 + 5e-9))
    assert compare_plans(RECORD, near) == []
    assert compare_plans(RECORD, far) == [
        Difference("flight_length_m", 1161.462732611519, far["flight_length_m"])
    ]


def test_nested_differences_are_found_once_per_top_level_field_in_record_order():
    other = replanned(
        optimisation={"rounds": 6829, "restarts": 1047},
        objective_per_sweep=[12.41126179173574, 0.5],
        n_viewpoints=190,
    )
    assert [d.key for d in compare_plans(RECORD, other)] == [
        "n_viewpoints",
        "objective_per_sweep",
        "optimisation",
    ]


def test_same_value_keeps_types_apart():
    assert same_value(1, 1.0)
    assert not same_value(True, 1)
    assert not same_value({"a": 1}, {"a": 1, "b": 2})
    assert not same_value([1, 2], [1, 2, 3])
    assert same_value("x", "x") and not same_value("x", "y")


def test_differences_line_shortens_long_values():
    line = differences_line([Difference("objective_per_sweep", list(range(30)), [0])])
    assert line == "differs in objective_per_sweep ([0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11... vs [0])"
    assert differences_line([]) == "equal"


def test_proxy_identity_needs_every_count_equal():
    metrics = {"proxy_n_sparse_points": 13237, "proxy_n_dense_points": 318052, "proxy_proxy_faces": 49999}
    assert proxy_is_records(metrics, dict(metrics))
    assert not proxy_is_records(metrics, metrics | {"proxy_n_dense_points": 318051})
    assert not proxy_is_records({}, {})  # a record without the counts proves nothing


def test_cell_overrides_compose_the_recorded_cell():
    metrics = {
        "scene_config": "church",
        "planner": "smith",
        "seed": 0,
        "budget": "low",
        "experiment": "default",
    }
    assert cell_overrides(metrics) == [
        "scene=church",
        "planner=smith",
        "seed=0",
        "budget=low",
        "experiment=default",
    ]
    with pytest.raises(ValueError, match="lacks budget"):
        cell_overrides({k: v for k, v in metrics.items() if k != "budget"})
    with pytest.raises(ValueError, match="scene.path"):
        cell_overrides(metrics | {"scene_config": "mesh"})


def test_views_line_counts_moved_and_turned_views():
    views = np.array(
        [[0.0, 0.0, 30.0, 90.0, -45.0], [10.0, 0.0, 30.0, 0.0, -90.0], [20.0, 5.0, 30.0, 0.0, -90.0]]
    )
    assert views_line(views, views.copy()) == "views: identical"
    other = views.copy()
    other[1, :3] += [3.0, 4.0, 0.0]  # 5 m
    other[2, 3] += 1.5
    assert views_line(views, other) == "views: 2 of 3 differ (up to 5.000 m, 1.50 deg)"
    assert views_line(views, views[:2]) == "views: 3 vs 2"


def test_a_folder_without_a_record_is_refused_in_one_line(tmp_path, capsys):
    assert main([str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"error: {tmp_path}:") and "metrics.json" in err and "\n" not in err
