"""Tests of gpguided_jax.analysis (coverage, GP surfaces) and the Fig. 2/4 + coverage script."""

import csv
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import run_script

from gpguided_jax import analysis, controllers, kernels, sparse_gp

SMALL = dict(num_angle_bins=4, num_velocity_bins=2, max_velocity=8.0)

# Hand-computed on a 4 x 2 grid (angle bins of pi/2; velocity bins [-8, 0) and [0, 8]):
#   (0.1, 0)        -> (0, 1)
#   (0.2, 0.1)      -> (0, 1)      same cell
#   (pi, -7.9)      -> (2, 0)
#   (2pi - .01, 7.99) -> (3, 1)
#   (1.0, 100)      -> (0, 1)      too fast: clipped into the outermost velocity bin
#   (-0.1, -3)      -> (3, 0)      phi wraps to 2pi - 0.1
STATES = np.array([[0.1, 0.0], [0.2, 0.1], [math.pi, -7.9], [2 * math.pi - 0.01, 7.99],
                   [1.0, 100.0], [-0.1, -3.0]])
EXPECTED_CELLS = {(0, 1), (2, 0), (3, 1), (3, 0)}


def test_coverage_matches_hand_computed_case():
    grid = np.asarray(analysis.visited_cells(jnp.asarray(STATES), **SMALL))
    assert grid.shape == (4, 2)
    assert {tuple(ij) for ij in np.argwhere(grid)} == EXPECTED_CELLS
    assert float(analysis.state_coverage(jnp.asarray(STATES), **SMALL)) == pytest.approx(4 / 8)
    # the first three states only: cells (0, 1) and (2, 0)
    assert float(analysis.state_coverage(jnp.asarray(STATES[:3]), **SMALL)) == pytest.approx(2 / 8)


def test_coverage_mask_and_leading_axes():
    mask = np.array([True, True, True, False, False, False])
    assert float(analysis.state_coverage(jnp.asarray(STATES), jnp.asarray(mask), **SMALL)) == 2 / 8
    # leading axes are flattened: (2, 3, 2) gives the same answer as (6, 2)
    cov = analysis.state_coverage(jnp.asarray(STATES.reshape(2, 3, 2)), **SMALL)
    assert float(cov) == pytest.approx(4 / 8)
    # the default grid: one state is one cell of 36 x 32
    one = analysis.state_coverage(jnp.array([[math.pi, 0.0]]))
    assert float(one) == pytest.approx(1 / (analysis.NUM_ANGLE_BINS * analysis.NUM_VELOCITY_BINS))


def test_coverage_under_jit_and_vmap():
    batch = jnp.asarray(np.stack([STATES, STATES[:3].repeat(2, axis=0)]))
    f = jax.jit(jax.vmap(lambda s: analysis.state_coverage(s, **SMALL)))
    np.testing.assert_allclose(np.asarray(f(batch)), [4 / 8, 2 / 8])


def test_gp_surface_equals_predict_at_the_controller_action():
    key_x, key_y, key_theta = jax.random.split(jax.random.PRNGKey(0), 3)
    hyper = kernels.make_kernel_params(jnp.array([1.0, 1.0, 2.0, 1.5]), 2.0, 0.1)
    xs = jax.random.normal(key_x, (30, 4))
    ys = jax.random.normal(key_y, (30,))
    gp = sparse_gp.update_batch(sparse_gp.init(10, 4), xs, ys, hyper, 0)
    ctrl = controllers.make_controller("linear")
    theta_c = jax.tree_util.tree_map(
        lambda p: 0.3 * jax.random.normal(key_theta, p.shape, p.dtype), ctrl.init())
    phi = jnp.linspace(0.0, 2 * math.pi, 5)
    omega = jnp.linspace(-3.0, 3.0, 4)
    value, var = jax.jit(analysis.gp_surface, static_argnums=2)(gp, hyper, ctrl, theta_c, phi, omega)
    assert value.shape == var.shape == (5, 4)
    for i in (0, 3):
        for j in (1, 2):
            s = jnp.array([phi[i], omega[j]])
            x = kernels.state_action_features(s, ctrl.apply(theta_c, s))
            m, v = sparse_gp.predict(gp, x, hyper)
            np.testing.assert_allclose(float(value[i, j]), float(m), rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(float(var[i, j]), float(v), rtol=1e-10, atol=1e-12)
    assert np.all(np.asarray(var) >= 0) and np.all(np.asarray(var) <= 2.0 + 1e-12)


@pytest.mark.cli
def test_figure_script_runs_end_to_end(tmp_path):
    run_script(["experiments/fig2_fig4_coverage.py", "--preset", "tiny", "--seeds", "2",
                "--num-updates", "2", "--checkpoints", "2", "--eval-episodes", "2", "--grid", "7",
                "--out", tmp_path])
    for name in ("fig2_variance.png", "fig4_value.png", "coverage.png", "fig2_variance.csv",
                 "fig4_value.csv", "coverage.csv", "coverage.json", "visited_states.csv",
                 "results.npz"):
        assert (tmp_path / name).stat().st_size > 0, name
    with open(tmp_path / "fig2_variance.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 2 * 2 * 7 * 7  # two views x two methods x grid
    assert {r["method"] for r in rows} == {"gp_pg", "guided_variance"}
    rel = np.array([float(r["rel"]) for r in rows])
    assert np.all((rel >= 0) & (rel <= 1 + 1e-9))
    cov = json.loads((tmp_path / "coverage.json").read_text())
    assert cov["checkpoints_at_updates"] == [1, 2]
    for m, per_seed in cov["per_seed"].items():
        assert len(per_seed) == 2 and all(0 < c <= 1 for c in per_seed), m
    with np.load(tmp_path / "results.npz") as f:
        assert f["mean_reward"].shape == (4, 2, 2)
        assert np.all(np.isfinite(f["mean_reward"]))
