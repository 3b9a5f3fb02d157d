"""The method registry (`gpguided_jax.methods`): the paper's four methods as declared specs, a
method registered inside a test running through every driver, and the priors `reproduce` fits
per method."""

import csv
import dataclasses
import json
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import REPRODUCE_KW

from gpguided_jax import cli, methods, settings, sharding, summaries
from gpguided_jax import config as C
from gpguided_jax import reproduce as R
from gpguided_jax import sweep as S
from gpguided_jax import train as T

PAPER = ("reinforce", "gp_pg", "guided_variance", "guided_direction")


def test_the_paper_methods_are_declared_and_the_drivers_read_their_declarations():
    assert C.METHODS[:4] == PAPER == C.PAPER_METHODS and "gp_critic" in C.METHODS
    assert T.GP_METHODS[:3] == PAPER[1:]
    assert [C.preset("tiny", method=m).uses_gp for m in PAPER] == [False, True, True, True]
    # the probability-of-improvement pairs, written out by hand
    assert methods.comparisons(PAPER) == (
        ("gp_pg", "reinforce"), ("guided_variance", "reinforce"), ("guided_direction", "reinforce"),
        ("guided_variance", "gp_pg"), ("guided_direction", "gp_pg"))
    assert methods.comparisons(["guided_direction", "gp_pg"]) == (("guided_direction", "gp_pg"),)
    # the three GP methods share one program; REINFORCE has its own
    assert T.program_family(C.preset("tiny", method="guided_variance")) == PAPER[1:]
    assert T.program_family(C.preset("tiny", method="reinforce")) == ("reinforce",)
    # under a scheme guided_direction refuses, the family is the methods that accept it
    assert T.program_family(C.preset("tiny", method="gp_pg", exploration="ou")) == PAPER[1:3]
    assert T.program_family(C.preset("tiny", method="gp_pg", exploration="parameter")) == ("gp_pg",)


@pytest.mark.parametrize("kw, words", [
    (dict(method="guided_direction", exploration="ou"), "guided_direction takes 'white' only, got "
     "'ou', which is for reinforce, gp_pg, guided_variance, gp_critic and gp_model only"),
    (dict(method="guided_variance", exploration="parameter"), "for reinforce and gp_pg only"),
    (dict(method="no_such_method"), "unknown method 'no_such_method'"),
])
def test_a_config_a_method_cannot_run_is_refused_in_its_words(kw, words):
    with pytest.raises(ValueError, match="TrainConfig") as e:
        C.preset("tiny", **kw)
    assert words in str(e.value)


def test_register_refuses_a_clash_and_an_incomplete_declaration():
    gp_pg = methods.get("gp_pg")
    with pytest.raises(ValueError, match="already registered"):
        methods.register(gp_pg)
    with pytest.raises(ValueError, match="shared records"):
        methods.register(gp_pg._replace(name="x", records=("mean_reward",)))
    with pytest.raises(ValueError, match="unknown prior"):
        methods.register(gp_pg._replace(name="x", prior="dynamics"))
    with pytest.raises(ValueError, match="fields its fit reads"):
        methods.register(gp_pg._replace(name="x", fit_fields=()))
    assert "x" not in methods.names()


def test_the_q_gp_fit_reads_its_declared_traced_fields_and_no_other():
    """`methods.Q_GP_FIT_FIELDS` decides which methods of a run share a fitted prior: a traced
    field outside it leaves the fit unchanged bit for bit, and each traced field in it changes
    it. One compiled fit, the config a traced argument."""
    cfg = C.preset("tiny", method="gp_pg")
    train = T.make_train(cfg)
    fit = jax.jit(lambda c: train.fit_kernel_for_seed(jax.random.PRNGKey(3), c))
    base = fit(cfg)

    def same(a, b):
        return all(np.array_equal(x, y) for x, y in zip(jax.tree_util.tree_leaves(a),
                                                        jax.tree_util.tree_leaves(b)))

    declared = set(methods.get("gp_pg").fit_fields)
    for f in C.TRACED_FIELDS:
        if f == "pendulum":
            changed = cfg.replace(pendulum=dataclasses.replace(
                cfg.pendulum, start_std=cfg.pendulum.start_std * 1.5))
        else:
            changed = cfg.replace(**{f: getattr(cfg, f) * 0.9})
        assert same(fit(changed), base) == (f not in declared), f


# ------------------------------------------------------------------------------------------------
# A method registered inside a test: random search over the controller's weights.
# ------------------------------------------------------------------------------------------------


@settings.declare(static=("patience",), prefix="climb_")
class HillClimbSettings:
    """The test method's own settings (flat names climb_step_size, climb_patience).

    Static:
      patience: after this many rejected tries in a row the step size halves.

    Traced:
      step_size: the scale of the Gaussian perturbation of the controller's weights.
    """

    patience: int = 2
    step_size: Any = 0.05

    def check(self, cfg) -> None:
        settings.integer("climb_patience", self.patience, 1)
        settings.traced("climb_step_size", self.step_size, positive=True)


@settings.declare(prefix="model_")
class _ClashingSettings:
    """A setting whose flat name is gp_model's."""

    horizon: float = 1.0

    def check(self, cfg) -> None:
        del cfg


class HillClimbState(NamedTuple):
    best_theta: object  # PolicyParams: the best parameters so far
    best_return: jax.Array  # () their episodes' mean return
    rejected: jax.Array  # () int32, tries rejected in a row


def _hill_climb_init(prog, key, cfg):
    del key
    return HillClimbState(T.initial_theta(prog, cfg), jnp.asarray(-jnp.inf, prog.dtype),
                          jnp.zeros((), jnp.int32))


def _hill_climb_update(prog, cfg, state, batch):
    """Keeps the parameters if their episodes' mean return beats the best so far, then tries the
    best plus Gaussian noise of the settings' step size (halved after every `patience` rejected
    tries in a row) on the controller's weights."""
    own = cfg.settings
    ret = jnp.mean(jnp.sum(batch.episodes.rewards, axis=1))
    best = state.method_state
    better = ret > best.best_return
    theta = jax.tree_util.tree_map(lambda n, o: jnp.where(better, n, o), state.theta,
                                   best.best_theta)
    best_return = jnp.maximum(ret, best.best_return)
    rejected = jnp.where(better, 0, best.rejected + 1)
    step = own.step_size * 0.5 ** (rejected // own.patience)
    leaves, tree = jax.tree_util.tree_flatten(theta.controller)
    keys = jax.random.split(jax.random.fold_in(state.key, 7), len(leaves))
    tried = [w + step * jax.random.normal(k, w.shape, w.dtype) for w, k in zip(leaves, keys)]
    new = theta._replace(controller=jax.tree_util.tree_unflatten(tree, tried))
    records = dict(best_return=best_return, accepted=better.astype(jnp.int32),
                   step_size=jnp.asarray(step, prog.dtype))
    return new, state.opt_state, HillClimbState(theta, best_return, rejected), records


HILL_CLIMB = methods.Method(
    name="hill_climb", policy="fixed_noise", prior="none", init=_hill_climb_init,
    update=_hill_climb_update, records=("best_return", "accepted", "step_size"),
    explorations=("white",), compare_with=("reinforce",),
    explain_exploration="hill_climb explores by its weights", settings=HillClimbSettings,
    policy_optimiser=False,
    # its own number of updates on the tiny preset (the paper's methods keep theirs)
    presets={"tiny": {"num_updates": 4, "climb_patience": 3}})


@pytest.fixture
def hill_climb():
    methods.register(HILL_CLIMB)
    yield HILL_CLIMB
    methods.unregister(HILL_CLIMB.name)


def test_a_method_with_its_own_settings_is_configured_by_their_flat_names(hill_climb):
    """Its settings: defaults, its preset, an override, their checks, another method's refused
    quietly, the config's JSON view and the static/traced split of the pytree."""
    cfg = C.preset("tiny", method="hill_climb", climb_step_size=0.2, critic_steps=7)
    assert isinstance(cfg.settings, HillClimbSettings)
    assert cfg.settings.patience == 3 and float(cfg.settings.step_size) == 0.2
    assert cfg.settings.step_size.dtype == jnp.float64  # traced: cast to the run's dtype
    assert C.preset("tiny", method="reinforce", climb_step_size=0.2).settings is None
    view = cfg.to_json_dict()
    assert view["climb_patience"] == 3 and view["climb_step_size"] == 0.2
    assert "critic_steps" not in view and cfg.static_dict()["climb_patience"] == 3
    assert float(cfg.value("climb_step_size")) == 0.2 and cfg.value("num_updates") == 4
    with pytest.raises(KeyError, match="critic_steps"):
        cfg.value("critic_steps")
    assert cfg.replace(climb_patience=5).settings.patience == 5
    assert cfg.replace(method="reinforce").settings is None
    leaves = jax.tree_util.tree_leaves(cfg.settings)
    assert len(leaves) == 1 and float(leaves[0]) == 0.2  # the static one is metadata
    with pytest.raises(ValueError, match="climb_patience: must be a positive integer, got 0"):
        C.preset("tiny", method="hill_climb", climb_patience=0)
    with pytest.raises(ValueError, match="climb_step_size: must be > 0"):
        C.preset("tiny", method="hill_climb", climb_step_size=-1.0)
    with pytest.raises(TypeError, match="climb_steps"):
        C.preset("tiny", method="hill_climb", climb_steps=1)
    with pytest.raises(ValueError, match=r"\['model_horizon'\] are already gp_model's"):
        methods.register(HILL_CLIMB._replace(name="x", settings=_ClashingSettings))
    assert "x" not in methods.names()


@pytest.mark.training
def test_a_method_registered_in_a_test_runs_through_every_driver(tmp_path, hill_climb, capsys):
    """The command line (with --set of the method's own settings; a chunk, then resumed from its
    checkpoint), its results file and summaries, and a sweep of its traced setting take the
    registered method as they take the paper's, beside REINFORCE with another number of updates
    and other records; `reproduce --help` lists its settings."""
    with pytest.raises(SystemExit):
        cli.main(["reproduce", "--help"])
    assert "hill_climb: climb_patience (2), climb_step_size (0.05)" in " ".join(
        capsys.readouterr().out.split())
    out_dir = str(tmp_path / "a")
    args = ["reproduce", "--preset", "tiny", "--seeds", "2", "--seed-start", "0", "--chunk-size",
            "2", "--methods", "hill_climb", "reinforce", "--keep-checkpoints", "--out", out_dir,
            "--set", "climb_step_size=0.2", "climb_patience=1"]
    assert cli.main(args + ["--max-chunks", "1"]) == 0
    assert (tmp_path / "a" / "checkpoint_hill_climb.npz").exists()
    capsys.readouterr()
    assert cli.main(args) == 0
    assert "[hill_climb] resuming" in capsys.readouterr().err

    with open(tmp_path / "a" / "config.json") as f:
        run = json.load(f)["methods"]
    assert run["hill_climb"]["climb_step_size"] == 0.2 and run["hill_climb"]["climb_patience"] == 1
    assert "climb_step_size" not in run["reinforce"]
    with np.load(tmp_path / "a" / "results.npz") as f:
        assert list(f["methods"]) == ["hill_climb", "reinforce"]
        assert list(f["num_updates"]) == [4, 6]
        assert f["mean_reward"].shape == (2, 2, 6)
        climb_return, climb_best = f["mean_return"][0, :, :4], f["best_return"][0, :, :4]
        # the method's own state went through every update and the resume from the checkpoint
        # (after 2 of its 4 updates): its best so far is the running maximum of its episodes'
        # returns, and its step size halves after each rejected try (patience 1 from --set)
        np.testing.assert_allclose(climb_best, np.maximum.accumulate(climb_return, axis=1))
        accepted = f["accepted"][0, :, :4]
        rejected = np.zeros_like(accepted)
        for u in range(4):
            rejected[:, u] = np.where(accepted[:, u] == 1, 0, (rejected[:, u - 1] if u else 0) + 1)
        np.testing.assert_allclose(f["step_size"][0, :, :4], 0.2 * 0.5 ** rejected)
        assert np.all(np.isnan(f["mean_reward"][0, :, 4:]))  # past its last update
        assert np.all(np.isnan(f["grad_norm"][0])) and np.all(np.isnan(f["best_return"][1]))
        assert np.all(np.isfinite(f["grad_norm"][1]))
        # the environment steps axis: 2 episodes of 20 steps per update, no fit for either, the
        # records of the update's own episodes (the tiny preset evaluates no policy apart)
        np.testing.assert_array_equal(f["env_steps"][1], 40.0 * np.arange(1, 7))
        np.testing.assert_array_equal(f["env_steps"][0, :4], 40.0 * np.arange(1, 5))
    with open(tmp_path / "a" / "summary.csv") as f:
        rows = {r["method"]: r for r in csv.DictReader(f)}
    assert set(rows) == {"reinforce", "hill_climb"}
    # records it does not keep are no failure; its own are all finite
    assert int(rows["hill_climb"]["fail_nonfinite_grad"]) == 0
    assert int(rows["hill_climb"]["fail_nan_record"]) == 0
    with open(tmp_path / "a" / "comparisons.csv") as f:
        assert [(r["x"], r["y"]) for r in csv.DictReader(f)] == [("hill_climb", "reinforce")]

    swept = S.run_sweep("climb_step_size", [0.01, 0.1], method="hill_climb", preset="tiny",
                        seeds=[0], progress=lambda m: None)
    assert swept.records["best_return"].shape == (2, 1, 4)
    assert [r["climb_step_size"] for r in swept.rows] == [0.01, 0.1]
    np.testing.assert_allclose(swept.records["step_size"][:, 0, 0], [0.01, 0.1])
    with pytest.raises(ValueError, match="climb_patience is a static field"):
        S.resolve_param("climb_patience")
    with pytest.raises(ValueError, match="it is a setting of hill_climb"):
        S.run_sweep("climb_step_size", [0.1], method="reinforce", preset="tiny", seeds=[0])


# ------------------------------------------------------------------------------------------------
# reproduce: the programs and the priors of the methods asked for.
# ------------------------------------------------------------------------------------------------


def test_reproduce_builds_the_shared_program_of_the_methods_that_accept_the_config():
    """`gpguided reproduce --methods gp_pg --exploration ou` builds the GP methods' one program
    only of the methods that accept OU noise (guided_direction refuses it): the chunk program
    `run_method` builds traces, for gp_pg and for guided_variance, to the records of each."""
    mesh = sharding.make_mesh(1)
    for m in ("gp_pg", "guided_variance"):
        cfg = C.preset("tiny", method=m, exploration="ou", num_updates=2)
        train = T.make_train(cfg)
        step = R.chunk_program(train, mesh, "map", 2)
        state = jax.eval_shape(lambda k, c=cfg, t=train: jax.vmap(t.init, in_axes=(0, None))(k, c),
                               sharding.seed_keys([0, 1]))
        _, rec = jax.eval_shape(step, state)
        assert rec.mean_reward.shape == (2, 2), m
    with pytest.raises(ValueError, match="guided_direction takes 'white' only"):
        C.preset("tiny", method="guided_direction", exploration="ou")


@pytest.mark.training
def test_each_method_runs_with_the_prior_fitted_from_its_own_settings(tmp_path, monkeypatch):
    """A method whose tuned settings change the fit's data (here its discount) runs with the
    prior fitted on its own data, and the methods whose fit inputs agree share one fit. The
    runs themselves are replaced by a stand-in that keeps the prior each is given; reference:
    each method's fit from its own config."""
    monkeypatch.setitem(methods.get("guided_variance").presets, "tiny", {"discount_horizon": 0.05})
    given = {}

    def run_method(cfg, seeds, out_dir, *, kernels=None, **kw):
        given[cfg.method] = kernels
        rec = T.record_type(methods.get(cfg.method))(*[np.zeros((len(seeds), cfg.num_updates))
                                                        for _ in T.record_fields(cfg.method)])
        return rec._asdict(), None

    monkeypatch.setattr(R, "run_method", run_method)
    seeds, three = [0, 1], ["gp_pg", "guided_variance", "guided_direction"]
    msgs = []
    R.reproduce(out_dir=str(tmp_path), progress=msgs.append,
                **dict(REPRODUCE_KW, seeds=seeds, methods=three))
    assert sum("hyperparameter fit" in m for m in msgs) == 2, msgs  # gp_pg's is shared
    mesh = sharding.make_mesh(None, len(seeds))
    for m in three:
        own = R.fit_program(T.make_train(C.preset("tiny", method=m)), mesh, "auto")(
            sharding.shard(sharding.seed_keys(seeds), mesh))
        np.testing.assert_array_equal(given[m].mean, np.asarray(own.mean), err_msg=m)
        np.testing.assert_array_equal(given[m].kernel.lengthscales,
                                      np.asarray(own.kernel.lengthscales), err_msg=m)
        with np.load(tmp_path / f"kernels_{m}.npz") as f:
            np.testing.assert_array_equal(f["prior_mean"], given[m].mean, err_msg=m)
    assert not np.allclose(given["gp_pg"].mean, given["guided_variance"].mean)
    assert given["gp_pg"] is given["guided_direction"]


def test_the_env_steps_axis_counts_the_fit_and_the_updates_before_each_record():
    # a fit of 10 episodes of 200 steps, then 5 episodes of 200 steps per update (Pendulum-v1's
    # preset); the deterministic policy's record u is taken after u updates' episodes, that of
    # the update's own episodes after u + 1 updates'
    budget = summaries.TaskBudget(steps_per_update=1000, fit_steps=2000, threshold=-200.0)
    np.testing.assert_array_equal(summaries.env_steps_axis(budget, 3), [2000, 3000, 4000])
    exploring = budget._replace(return_record="mean_return")
    np.testing.assert_array_equal(summaries.env_steps_axis(exploring, 3), [3000, 4000, 5000])
    reach = summaries.steps_to_threshold(np.array([[-300.0, -150.0, -100.0]]), budget)
    np.testing.assert_array_equal(reach, [3000])


def test_every_config_field_is_in_exactly_one_group():
    """Every field the loop shares is in one group; a method's settings are its own."""
    grouped = [f for fields in C.FIELD_GROUPS.values() for f in fields]
    assert sorted(grouped + ["settings"]) == sorted(f.name for f in dataclasses.fields(C.TrainConfig))
    assert len(grouped) == len(set(grouped))
    assert C.group_of("trust_region") == "gp_critic" and C.group_of("gp_capacity") == "gp"
    assert C.group_of("model_horizon") == "gp_model"
    with pytest.raises(KeyError):
        C.group_of("critic_bogus")
