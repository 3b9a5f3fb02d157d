"""Tests of gpguided_jax.sweep and the `gpguided sweep` command."""

import csv
import os
import subprocess
import sys

import numpy as np
import pytest
from conftest import fast_compile_env

from gpguided_jax import cli
from gpguided_jax import sweep as S


@pytest.mark.parametrize(
    "name,field",
    [("lambda", "age_penalty"), ("beta", "inverse_temperature"), ("lr", "learning_rate"),
     ("age_penalty", "age_penalty"), ("energy_width", "energy_width")],
)
def test_resolve_param_and_aliases(name, field):
    assert S.resolve_param(name) == field


@pytest.mark.parametrize("name", ["gp_capacity", "num_updates", "method", "controller"])
def test_static_fields_are_refused_naming_the_field(name):
    with pytest.raises(ValueError, match=f"TrainConfig.{name} is a static field"):
        S.resolve_param(name)


@pytest.mark.parametrize("name", ["lamda", "bogus", "pendulum"])
def test_unknown_fields_are_refused_naming_the_field(name):
    with pytest.raises(ValueError, match=name):
        S.resolve_param(name)


def test_bad_value_is_refused_naming_the_field():
    with pytest.raises(ValueError, match="inverse_temperature"):
        S.run_sweep("beta", [1.0, -1.0], method="guided_direction", preset="tiny", seeds=[0])


def test_even_chunk_size():
    assert S.even_chunk_size(400, 50) == 50
    assert S.even_chunk_size(400, 60) == 50
    assert S.even_chunk_size(7, 3) == 1
    assert S.even_chunk_size(6, 50) == 6
    assert S.even_chunk_size(6, 4) == 3


def test_x_scale():
    assert S._x_scale(np.array([1e-4, 1e-3, 1e-2]))[0] == "log"
    assert S._x_scale(np.array([0.0, 10, 100, 1000])) == ("symlog", {"linthresh": 10.0})
    assert S._x_scale(np.array([1.0, 2.0, 3.0]))[0] == "linear"
    assert S._x_scale(np.array([-1.0, 10.0, 100.0]))[0] == "linear"


# The two tests below sweep the tiny preset's gp_pg over 3 values x 2 seeds: one program of the
# same shapes, compiled by the first and loaded from the test run's compilation cache by the
# second (in one worker, one after the other).
@pytest.mark.training
@pytest.mark.xdist_group("tiny_sweep")
def test_sweep_is_one_program_and_writes_its_files(tmp_path, monkeypatch):
    traces = {"init": 0, "run_chunk": 0}
    make_train = S.train_lib.make_train

    def counting_make_train(cfg):
        train = make_train(cfg)
        init, run_chunk = train.init, train.run_chunk

        def counted_init(*a, **k):
            traces["init"] += 1  # Python runs only while JAX traces
            return init(*a, **k)

        def counted_run_chunk(*a, **k):
            traces["run_chunk"] += 1
            return run_chunk(*a, **k)

        train.init, train.run_chunk = counted_init, counted_run_chunk
        return train

    monkeypatch.setattr(S.train_lib, "make_train", counting_make_train)
    lines = []
    result = S.run_sweep("lambda", [0.0, 1000.0, 10.0], method="gp_pg", preset="tiny",
                         seeds=[0, 1], overrides={"num_updates": 4}, chunk_size=2,
                         progress=lines.append)
    # 3 values x 2 seeds x 2 chunks: one init program and one chunk program
    assert traces == {"init": 1, "run_chunk": 1}
    assert result.param == "age_penalty"
    assert result.records["mean_reward"].shape == (3, 2, 4)
    assert all(np.all(np.isfinite(v)) for v in result.records.values())
    # same seeds for every value: the first episodes (before any GP-driven update) coincide
    r0 = result.records["mean_reward"][:, :, 0]
    np.testing.assert_allclose(r0, np.broadcast_to(r0[:1], r0.shape))
    assert [r["age_penalty"] for r in result.rows] == [0.0, 1000.0, 10.0]
    assert any("updates 2/4" in s for s in lines) and any("updates 4/4" in s for s in lines)

    paths = S.write_sweep(result, str(tmp_path), preset="tiny")
    for p in paths.values():
        assert os.path.getsize(p) > 0, p
    with open(paths["csv"]) as f:
        rows = list(csv.DictReader(f))
    assert [float(r["age_penalty"]) for r in rows] == [0.0, 1000.0, 10.0]
    for r in rows:
        assert float(r["ci95_low"]) <= float(r["final_mean"]) <= float(r["ci95_high"])
        assert 0 <= float(r["fresh_bv_share_mean"]) <= 1
        assert r["seeds_with_skipped_updates"] == "0"
    with np.load(paths["results"]) as f:
        assert str(f["param"]) == "age_penalty"
        assert f["mean_reward"].shape == (3, 2, 4)


@pytest.mark.cli
def test_cli_sweep_in_a_subprocess(tmp_path):
    out = tmp_path / "sweep"
    cmd = [sys.executable, "-m", "gpguided_jax.cli", "sweep", "--param", "lr", "--values", "1e-4",
           "1e-3", "1e-2", "--method", "reinforce", "--preset", "tiny", "--seeds", "2",
           "--num-updates", "2", "--out", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=fast_compile_env())
    assert proc.returncode == 0, proc.stderr
    assert "| learning_rate |" in proc.stdout
    assert "[sweep learning_rate] done in" in proc.stderr
    for name in ("results.npz", "sweep.csv", "config.json", "sweep_learning_rate.png"):
        assert (out / name).stat().st_size > 0, name


@pytest.mark.parametrize("param,field", [("gp_capacity", "gp_capacity"), ("lamda", "lamda")])
def test_cli_refuses_bad_params_naming_the_field(param, field, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["sweep", "--param", param, "--values", "1", "2", "--preset", "tiny"])
    assert field in str(e.value.code)


def test_cli_sweep_help(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["sweep", "--help"])
    assert e.value.code == 0
    assert "--param" in capsys.readouterr().out


@pytest.mark.training
@pytest.mark.xdist_group("tiny_sweep")  # see test_sweep_is_one_program_and_writes_its_files
def test_sweep_runs_equal_the_same_runs_alone(tmp_path):
    """On a CPU the sweep takes its runs one after another (`sharding.per_seed_program`, map):
    a (value, seed) run's records are those of `reproduce.run_method` for that value's config and
    the same fitted kernels, bit for bit, with the method's own program (a sweep compiles one
    method; `gp_program='per_method'`)."""
    import jax

    from gpguided_jax import config as C
    from gpguided_jax import reproduce, sharding

    values, seeds = [0.001, 0.01, 0.1], [3, 4]
    result = S.run_sweep("lr", values, method="gp_pg", preset="tiny", seeds=seeds,
                         overrides={"num_updates": 4}, chunk_size=2, progress=lambda m: None)
    mesh = sharding.make_mesh(1)
    fit = S.train_lib.make_train(C.preset("tiny", method="gp_pg")).fit_kernel_for_seed
    priors = jax.device_get(sharding.per_seed_program(fit, mesh)(sharding.seed_keys(seeds)))
    # the second value's runs alone (the first value's differ, so a mix-up of values would show)
    assert not np.array_equal(result.records["grad_norm"][0], result.records["grad_norm"][1])
    cfg = C.preset("tiny", method="gp_pg", num_updates=4, learning_rate=values[1])
    rec, _ = reproduce.run_method(cfg, seeds, str(tmp_path), chunk_size=2, mesh=mesh,
                                  kernels=priors, progress=lambda m: None, gp_program="per_method")
    for k in ("mean_reward", "exploration_std", "grad_norm", "num_basis_vectors"):
        np.testing.assert_array_equal(result.records[k][1], rec[k])
