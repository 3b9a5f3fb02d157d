"""End-to-end tests of Algorithm 1 (gpguided_jax.train) and the chunked reproduce driver."""

import functools
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from conftest import REPRODUCE_KW, TWO_DEVICE_ARGS, run_script

from gpguided_jax import config as C
from gpguided_jax import estimators, sharding, summaries
from gpguided_jax import reproduce as R
from gpguided_jax import train as T

KEYS = jax.random.split(jax.random.PRNGKey(0), 2)
# the paper's three GP methods: the family of one program (`train.program_family`)
PAPER_GP = T.program_family(C.preset("tiny", method="gp_pg"))


TINY_TRACES: dict = {}  # program ("reinforce" or "gp_methods") -> how often it was traced


@functools.cache
def _tiny_gp_program():
    """(train, shared) of the tiny preset's GP methods, made once and outside any trace."""
    base = C.preset("tiny", method="gp_pg")
    return T.make_train(base), T.make_gp_methods_train(base)


@functools.cache
def _tiny_priors():
    """The tiny preset's hyperparameter fit for the seeds KEYS (gp_pg's, which the three GP methods
    share), compiled and run once in a worker for the tests that start from fitted priors."""
    fit = T.make_train(C.preset("tiny", method="gp_pg")).fit_kernel_for_seed
    return jax.jit(jax.vmap(fit))(KEYS)


def _tiny_prior(i):
    """Seed i's prior from `_tiny_priors`."""
    return jax.tree_util.tree_map(lambda x: x[i], _tiny_priors())


def _tiny_gp_run(key, index, cfg):
    """One seed's whole tiny run of the GP method `index` (config `cfg`) through the three GP
    methods' one program (`train.make_gp_methods_train`), as `gpguided reproduce` runs them."""
    train, shared = _tiny_gp_program()
    state = train.init(key, cfg)  # the hyperparameter fit, then the initial state
    return shared(state, index, cfg, train.config.num_updates)


@pytest.fixture(scope="session")
def tiny_runs():
    """Every method's tiny run, computed once, as `gpguided reproduce` runs it on a CPU: each
    seed's own program one after another on one device (`sharding.per_seed_program`, 'map'),
    REINFORCE with its own program and the three GP methods with their one shared program (each
    method's own program against it: test_gp_methods_program_runs_each_method_as_its_own_program).
    The tests that use it are in one xdist group (`make test` runs `--dist loadgroup`), so that
    one worker computes it, not each, and the fixture is session-scoped, so that the worker does
    not recompute it whenever other modules' tests come in between. `TINY_TRACES` counts each
    program's traces. Returns method -> (run, its arguments, its (state, records))."""
    mesh = sharding.make_mesh(1)
    reinforce = T.make_train(C.preset("tiny", method="reinforce"))
    _tiny_gp_program()

    def counted(name, fn):
        def run(*args):
            TINY_TRACES[name] = TINY_TRACES.get(name, 0) + 1  # runs only while tracing
            return fn(*args)
        return sharding.per_seed_program(run, mesh, "map")

    runs = {"reinforce": (counted("reinforce", reinforce), (KEYS,))}
    gp_program = counted("gp_methods", _tiny_gp_run)
    for m in PAPER_GP:
        # the method's index and config, one row per seed, as `reproduce` passes them
        runs[m] = (gp_program, (KEYS, *R.gp_method_args(C.preset("tiny", method=m), len(KEYS), mesh)))
    return {m: (fn, args, fn(*args)) for m, (fn, args) in runs.items()}


@pytest.mark.training
@pytest.mark.xdist_group("tiny_runs")
@pytest.mark.parametrize("method", C.PAPER_METHODS)
def test_every_method_runs_with_finite_records(tiny_runs, method):
    _, _, (state, rec) = tiny_runs[method]
    cfg = C.preset("tiny")
    for name, v in rec._asdict().items():
        v = np.asarray(v)
        assert v.shape == (2, cfg.num_updates), name
        assert np.all(np.isfinite(v)), name
    assert np.all(np.asarray(rec.nonfinite_grad) == 0)
    assert np.all(np.asarray(rec.gp_guard) == 0)
    assert np.all(np.asarray(state.update_index) == cfg.num_updates)
    leaves = jax.tree_util.tree_leaves(state.theta)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in leaves)
    if method == "reinforce":
        assert np.all(np.asarray(rec.num_basis_vectors) == 0)
    else:
        assert np.all(np.asarray(rec.num_basis_vectors) > 0)
        assert np.all(np.asarray(rec.num_basis_vectors) <= cfg.gp_capacity)


@pytest.mark.training
@pytest.mark.xdist_group("tiny_runs")
def test_the_paper_methods_records_equal_their_reference_file(tiny_runs):
    """The tiny preset's records of the paper's four methods, run as `gpguided reproduce` runs
    them, are those of tests/data/paper_methods_tiny_records.npz (float64): a change of the
    training loop's structure must leave the paper's methods' numbers as they are. The
    tolerance allows for another CPU's vector width, no more (the file's own machine reproduces
    it bit for bit)."""
    with np.load(os.path.join(os.path.dirname(__file__), "data",
                              "paper_methods_tiny_records.npz")) as ref:
        assert sorted(ref.files) == sorted(f"{m}/{k}" for m in C.PAPER_METHODS for k in T.RECORD_FIELDS)
        for name in ref.files:
            method, field = name.split("/")
            got = np.asarray(getattr(tiny_runs[method][2][1], field))
            np.testing.assert_allclose(got, ref[name], rtol=1e-9, atol=1e-12, err_msg=name)


@pytest.mark.training
@pytest.mark.xdist_group("tiny_runs")
@pytest.mark.parametrize("method", ["reinforce", "guided_variance", "guided_direction"])
def test_same_key_bitwise_identical_no_recompile_and_seeds_differ(tiny_runs, method):
    """A second call of the compiled run gives the same records bit for bit and does not trace
    (nor compile) again, and the three GP methods' program was traced once for the three; the
    two seeds differ."""
    fn, args, (_, rec) = tiny_runs[method]
    _, rec2 = fn(*args)
    assert TINY_TRACES == {"reinforce": 1, "gp_methods": 1}
    for a, b in zip(rec, rec2):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    r = np.asarray(rec.mean_reward)
    assert not np.array_equal(r[0], r[1])


@pytest.mark.training
@pytest.mark.xdist_group("tiny_runs")
def test_per_seed_program_map_equals_one_seed_alone(tiny_runs):
    """The CPU default runs each seed's own program: a batch gives each seed exactly what it gets
    alone (jit of the unbatched function)."""
    _, (keys, index, cfg), (_, batch) = tiny_runs["guided_variance"]
    alone = jax.jit(lambda *a: _tiny_gp_run(*a)[1].mean_reward)
    for i in range(len(KEYS)):
        one_seed = jax.tree_util.tree_map(lambda x, i=i: x[i], (keys, index, cfg))
        np.testing.assert_array_equal(np.asarray(batch.mean_reward)[i], np.asarray(alone(*one_seed)))
    mesh = sharding.make_mesh(1)
    assert sharding.resolve_seed_loop("auto", mesh) == "map"
    with pytest.raises(ValueError, match="seed_loop"):
        sharding.resolve_seed_loop("pmap", mesh)


@pytest.mark.training
def test_sweep_over_traced_field_is_one_program():
    cfg = C.preset("tiny", method="gp_pg")
    train = T.make_train(cfg)
    lams = np.array([0.0, 10.0, 1000.0])
    cfgs = jax.tree_util.tree_map(lambda *xs: np.stack(xs), *[cfg.replace(age_penalty=v) for v in lams])
    keys = jax.random.split(jax.random.PRNGKey(3), 3)
    _, rec = jax.jit(jax.vmap(train))(keys, cfgs)
    assert np.asarray(rec.mean_reward).shape == (3, cfg.num_updates)
    # the age penalty is effective: the largest lambda keeps the most fresh basis vectors
    fresh = np.asarray(rec.fresh_bv_share)[:, -3:].mean(1)
    assert fresh[2] >= fresh[0]


@pytest.mark.parametrize(
    "field,value",
    [
        ("method", "sarsa"),
        ("num_updates", 0),
        ("episode_length", -5),
        ("gp_capacity", 0),
        ("num_candidates", 1),
        ("inverse_temperature", 0.0),
        ("inverse_temperature", -1.0),
        ("energy_width", 0.0),
        ("learning_rate", float("nan")),
        ("discount", 1.5),
        ("age_penalty", -1.0),
        ("controller", "mlp"),
        ("age_fn", "linear"),
        ("optimizer", "lbfgs"),
        ("gp_stride", 0),
        ("hyperfit_optimizer", "sgd"),
        ("eval_episodes", -1),
        ("success_hold_time", 0.0),
    ],
)
def test_bad_config_is_refused_naming_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        C.preset("tiny", **{field: value})


def test_unknown_preset_and_field():
    with pytest.raises(ValueError, match="preset"):
        C.preset("nope")
    with pytest.raises(TypeError, match="bogus"):
        C.preset("tiny", bogus=1)


IMPROVE_SEEDS = jax.random.split(jax.random.PRNGKey(42), 4)


def _improve_config(method):
    return C.preset("paper", method=method, num_updates=120, gp_capacity=30)


@pytest.fixture(scope="session")  # see `tiny_runs`
def improve_priors():
    """The seeds' hyperparameter fit, done once: it depends only on the seed's initial data, so the
    three GP methods share it (as `gpguided reproduce` does)."""
    return jax.jit(jax.vmap(T.make_train(_improve_config("gp_pg")).fit_kernel_for_seed))(IMPROVE_SEEDS)


@pytest.fixture(scope="session")
def improve_program():
    """The three GP methods' one program (`train.make_gp_methods_train`, as `gpguided reproduce`
    runs them) over the seeds, from their keys and priors: compiled once for the three tests."""
    cfg = _improve_config("gp_pg")
    train, shared = T.make_train(cfg), T.make_gp_methods_train(cfg)
    return jax.jit(jax.vmap(lambda k, p, i, c: shared(train.init(k, c, p), i, c, cfg.num_updates),
                            in_axes=(0, 0, None, None)))


@pytest.mark.training
@pytest.mark.xdist_group("improve")  # one worker fits the shared priors and compiles the program
@pytest.mark.parametrize("method", ["gp_pg", "guided_variance", "guided_direction"])
def test_gp_methods_improve_on_a_small_problem(method, improve_priors, improve_program):
    """The paper preset's task at a reduced size (120 updates, M = 30; 4 fixed seeds), with the
    preset's hyperparameter fit, Gibbs candidates and gradient clipping.

    Loose threshold: the mean reward per step over the last 20 updates beats the first 20 by
    0.01 on average over the seeds (measured: +0.037 to +0.085; the noise-free optimum is ~0.1
    above the start). Earlier versions of this test also shrank the hyperparameter fit (500
    samples) and the candidates (K = 8); with those, guided_variance and guided_direction did not
    improve on some seeds. The methods run as `gpguided reproduce` runs them, one program for the
    three (each method's own program: `tiny_runs`, and equal to rounding:
    test_gp_methods_program_runs_each_method_as_its_own_program).
    """
    cfg = _improve_config(method)
    _, rec = improve_program(IMPROVE_SEEDS, improve_priors, np.int32(PAPER_GP.index(method)),
                             T.gp_methods_key(cfg))
    r = np.asarray(rec.mean_reward)
    assert r[:, -20:].mean() > r[:, :20].mean() + 0.01, (r[:, :20].mean(1), r[:, -20:].mean(1))
    assert np.all(np.asarray(rec.gp_guard) == 0) and np.all(np.asarray(rec.nonfinite_grad) == 0)


@pytest.mark.training
def test_resume_equals_uninterrupted(tmp_path):
    kw = dict(REPRODUCE_KW, methods=["gp_pg"])
    full = R.reproduce(out_dir=str(tmp_path / "full"), progress=lambda m: None, **kw)
    assert full["complete"]
    part = R.reproduce(out_dir=str(tmp_path / "part"), max_chunks=1, progress=lambda m: None, **kw)
    assert not part["complete"]
    msgs = []
    resumed = R.reproduce(out_dir=str(tmp_path / "part"), progress=msgs.append, **kw)
    assert resumed["complete"] and any("resuming" in m for m in msgs)
    a = np.load(tmp_path / "full" / "results.npz")
    b = np.load(tmp_path / "part" / "results.npz")
    for k in ("mean_reward", "exploration_std", "grad_norm", "num_basis_vectors"):
        np.testing.assert_array_equal(a[k], b[k])
    assert (tmp_path / "full" / "summary.csv").exists()
    assert (tmp_path / "full" / "fig5_reward.png").exists()


@pytest.mark.distributed
@pytest.mark.xdist_group("two_devices")  # shares two_device_run with tests/test_distributed.py
def test_two_host_devices_vmapped_agree_with_each_seed_alone(tmp_path, two_device_run):
    """Runs the CLI in a subprocess with 2 forced host CPU devices.

    Seeds 0-3 sharded over 2 devices: ``--seed-loop vmap`` (what an accelerator runs) against
    ``auto`` (`two_device_run`). On a CPU ``auto`` is map, so each device runs its seeds one after
    another and a seed's result depends neither on its batch-mates
    (`test_per_seed_program_map_equals_one_seed_alone`) nor on the device count (two processes
    of one device each give `two_device_run` bit for bit: tests/test_distributed.py). With vmap,
    XLA compiles the batch differently and last-ulp differences (~2.5e-9 relative after 6
    updates) grow through training (to ~1e-5 in the gradient norm); agreement is asserted at 1e-4
    relative, far below any difference between seeds (~1e-1).
    """
    out = tmp_path / "vmap"
    run_script(["-m", "gpguided_jax.cli", *TWO_DEVICE_ARGS, "--seed-loop", "vmap", "--out", out],
               fast_compile="level0",  # as `two_device_run`
               XLA_FLAGS="--xla_force_host_platform_device_count=2")
    for loop, d in (("map", two_device_run), ("vmap", out)):
        config = json.loads((d / "config.json").read_text())
        assert config["devices"] == ["TFRT_CPU_0", "TFRT_CPU_1"] and config["seed_loop"] == loop
    mapped, batched = (np.load(d / "results.npz") for d in (two_device_run, out))
    assert not np.array_equal(mapped["mean_reward"][0, 0], mapped["mean_reward"][0, 1])
    for k in ("mean_reward", "exploration_std", "grad_norm", "num_basis_vectors", "gp_guard"):
        np.testing.assert_allclose(batched[k], mapped[k], rtol=1e-4, atol=1e-9)


def test_devices_for_seeds_keeps_the_load_and_minimises_padding():
    # (seeds, available devices) -> devices used: ceil(seeds / available) seeds on each
    for seeds, available, used in ((100, 64, 50), (10, 2, 2), (11, 2, 2), (1, 2, 1), (3, 2, 2),
                                   (5, 4, 3), (7, 1, 1)):
        got = sharding.devices_for_seeds(seeds, available)
        assert got == used, (seeds, available, got)
        assert -(-seeds // got) == -(-seeds // available)  # the same seeds per device
        assert got * -(-seeds // got) - seeds < -(-seeds // got)  # less than one device's padding
    with pytest.raises(ValueError):
        sharding.devices_for_seeds(0, 2)


@pytest.mark.training
def test_learnable_sigma_is_clipped_to_its_bounds():
    cfg = C.preset("tiny", method="reinforce", learning_rate=1.0, min_std=0.7, max_std=0.8)
    state, rec = jax.jit(T.make_train(cfg))(jax.random.PRNGKey(5))
    std = np.exp(np.asarray(state.theta.log_std))
    assert 0.7 - 1e-12 <= std <= 0.8 + 1e-12
    # the first update's episodes use the initial sigma (1.5); every later one a clipped sigma
    assert np.all(np.asarray(rec.exploration_std)[1:] <= 0.8 + 1e-12)
    # std_at_bound[i] records the sigma after update i, which update i + 1's episodes use
    at_bound = np.asarray(rec.std_at_bound).astype(bool)
    std_next = np.asarray(rec.exploration_std)[1:]
    np.testing.assert_array_equal(at_bound[:-1], np.isclose(std_next, 0.7) | np.isclose(std_next, 0.8))
    assert at_bound.any()  # lr 1 pushes sigma onto a bound
    with pytest.raises(ValueError, match="min_std"):
        C.preset("tiny", min_std=2.0, max_std=1.0)


@pytest.mark.training
def test_float32_run_keeps_every_array_in_float32():
    """dtype='float32' with JAX's x64 mode ON: nothing may be promoted to float64 on the way.
    guided_direction: the GP update, its mean in the gradient, and the Gibbs policy (the other
    policies in float32: tests/test_policies.py)."""
    for method in ("guided_direction",):
        cfg = C.preset("tiny", method=method, dtype="float32")
        state, rec = jax.jit(jax.vmap(T.make_train(cfg)))(KEYS)
        floats = [x for x in jax.tree_util.tree_leaves((state, rec))
                  if jnp.issubdtype(x.dtype, jnp.floating)]
        assert floats and all(x.dtype == jnp.float32 for x in floats), {x.dtype for x in floats}
        assert all(np.all(np.isfinite(np.asarray(x))) for x in floats)


@pytest.mark.training
def test_same_seed_sees_the_same_noise_in_both_dtypes():
    """Random draws are dtype-independent: REINFORCE's float32 and float64 curves agree to float32
    rounding (a float32-vs-float64 comparison then measures numerics, not different noise)."""
    recs = {}
    for dtype in ("float32", "float64"):
        cfg = C.preset("tiny", method="reinforce", dtype=dtype)
        recs[dtype] = np.asarray(jax.jit(T.make_train(cfg))(KEYS[0])[1].mean_reward, np.float64)
    np.testing.assert_allclose(recs["float32"], recs["float64"], rtol=1e-4)


def test_gradient_clipping_bounds_the_step():
    cfg = C.preset("tiny", method="reinforce", learning_rate=1e-3, max_grad_norm=2.0)
    prog = T.make_program(cfg)
    state = T.initial_state(prog, jax.random.PRNGKey(0), cfg)
    huge = jax.tree_util.tree_map(lambda x: jnp.full_like(x, 1e6), state.theta)
    theta, _, norm, finite, _ = T.optimiser_step(state, huge, cfg)
    step = jax.tree_util.tree_map(lambda a, b: a - b, theta, state.theta)
    step_norm = float(optax.global_norm(step._replace(log_std=jnp.zeros(()))))
    assert bool(finite) and float(norm) > 1e6 and step_norm <= 1e-3 * 2.0 * (1 + 1e-6)
    off = cfg.replace(max_grad_norm=jnp.asarray(jnp.inf))
    theta_off, *_ = T.optimiser_step(state, huge, off)
    assert float(jnp.max(jnp.abs(theta_off.controller.weights - state.theta.controller.weights))) > 100
    nan = jax.tree_util.tree_map(lambda x: jnp.full_like(x, jnp.nan), state.theta)
    theta_nan, _, _, finite, _ = T.optimiser_step(state, nan, cfg)
    assert not bool(finite)
    np.testing.assert_array_equal(theta_nan.controller.weights, state.theta.controller.weights)


@pytest.mark.training
def test_gp_guard_rejects_a_diverged_gp_and_counts_it():
    cfg = C.preset("tiny", method="gp_pg")
    prog = T.make_program(cfg)
    state = jax.jit(lambda k, p: T.initial_state(prog, k, cfg, p))(jax.random.PRNGKey(1),
                                                                   _tiny_prior(1))
    ep = jax.jit(lambda s: T.rollout(prog, jax.random.PRNGKey(2), s.theta,
                                     T.policy_context(cfg, s.gp, s.kernel), prog.policy, cfg))(state)
    returns = estimators.discounted_returns(ep.rewards, cfg.discount)
    xs = jax.vmap(T.kernels.state_action_features)(ep.states, ep.actions)
    take_in = jax.jit(lambda gp, t: T.take_in_episode(gp, state.kernel, xs, returns, t, cfg))
    gp, fired, _ = take_in(state.gp, 0)
    assert int(fired) == 0 and int(T.sparse_gp.num_basis_vectors(gp)) > 0
    # A finite but diverged GP (alpha blown up, as the first implementation's) is not taken in.
    bad = gp._replace(alpha=gp.alpha * 1e30)
    gp2, fired2, health = take_in(bad, 1)
    assert int(fired2) == 1 and float(health.mean_error_ratio) > 1
    for a, b in zip(jax.tree_util.tree_leaves(gp2), jax.tree_util.tree_leaves(bad)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.training
def test_gp_stride_takes_every_kth_point_into_the_gp():
    """With gp_stride = k the GP's update equals `take_in_episode` on points 0, k, 2k, ... of each
    episode; gp_stride = 1 is the default and unchanged."""
    cfg = C.preset("tiny", method="gp_pg", gp_stride=3, novelty_tol=0.0)
    prog = T.make_program(cfg)
    train = T.make_train(cfg)
    # compiled (faster than op by op), from a fitted prior
    state = jax.jit(lambda k, p: train.init(k, cfg, p))(jax.random.PRNGKey(3), _tiny_prior(0))
    new_state, _ = jax.jit(lambda s: T.one_update(prog, cfg, s))(state)

    @jax.jit
    def replay(state):  # the same episodes, by hand
        _, key_eps = jax.random.split(state.key)
        gp = state.gp
        for key_e in jax.random.split(key_eps, cfg.episodes_per_update):
            ctx = T.policy_context(cfg, gp, state.kernel)
            ep = T.rollout(prog, key_e, state.theta, ctx, prog.policy, cfg)
            ret = estimators.discounted_returns(ep.rewards, cfg.discount)
            feats = T.features(prog, ep.states, ep.actions)
            gp, _, _ = T.take_in_episode(gp, state.kernel, feats[::3], ret[::3], state.update_index,
                                         cfg)
        return gp

    gp = replay(state)
    np.testing.assert_array_equal(np.asarray(new_state.gp.mask), np.asarray(gp.mask))
    np.testing.assert_allclose(np.asarray(new_state.gp.alpha), np.asarray(gp.alpha), rtol=1e-10,
                               atol=1e-12)
    # fewer points than the whole episodes: the strided GP holds at most ceil(H / 3) per episode
    n = int(T.sparse_gp.num_basis_vectors(new_state.gp))
    assert 1 <= n <= cfg.episodes_per_update * -(-cfg.episode_length // 3)


def test_summary_success_columns():
    recs = {"mean_reward": np.zeros((3, 10)),
            "success_rate": np.array([[0.0] * 9 + [1.0], [0.0] * 10, [1.0] * 10]),
            "eval_success_rate": np.array([[0.0] * 9 + [1.0], [0.0] * 10, [0.5] * 10])}
    row = summaries.summarise({"m": recs}, success=True)[0]
    assert row["final_success_rate"] == pytest.approx((1.0 + 0.0 + 1.0) / 3)
    assert row["final_eval_success_rate"] == pytest.approx((1.0 + 0.0 + 0.5) / 3)
    assert row["seeds_eval_success_90"] == 1
    assert "final_success_rate" not in summaries.summarise({"m": recs})[0]
    md = summaries.summary_markdown([row])
    assert "success (c(s))" in md and "1/3" in md


# ------------------------------------------------------------------------------------------------
# The GP methods as one program (`train.make_gp_methods_train`, `reproduce.chunk_program`).
# ------------------------------------------------------------------------------------------------


def _assert_same_run_to_rounding(a, b, first_rtol=1e-11, rtol=1e-6):
    """Two runs of the same draws compiled differently: the same integer records (GP decisions,
    clipping, guard), the first update's floats equal to rounding (`first_rtol`), and the later
    ones within `rtol`. Rounding differences grow through the closed loop (the GP's choices feed
    the next roll-out): measured on the tiny preset, from ~1e-14 at the first update to ~1e-7 at
    the eighth (guided_direction); a real difference (another learning rate or method) moves
    them by more than 1e-3 (the negative checks below)."""
    (sa, ra), (sb, rb) = a, b
    for name, x in ra._asdict().items():
        x, y = np.asarray(x), np.asarray(getattr(rb, name))
        if np.issubdtype(x.dtype, np.integer):
            np.testing.assert_array_equal(x, y, err_msg=name)
        else:
            np.testing.assert_allclose(x[:, 0], y[:, 0], rtol=first_rtol, atol=1e-13, err_msg=name)
            np.testing.assert_allclose(x, y, rtol=rtol, atol=1e-12, err_msg=name)
    for x, y in zip(jax.tree_util.tree_leaves(sa.theta), jax.tree_util.tree_leaves(sb.theta)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=1e-12)


def _max_rel_diff(a, b):
    return max(float(np.max(np.abs(np.asarray(x) - np.asarray(y)) / (np.abs(np.asarray(y)) + 1e-12)))
               for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))


@pytest.mark.training
def test_gp_methods_program_runs_each_method_as_its_own_program():
    """One program for the three GP methods: with the method's index and config as arguments it
    gives what that method's own program gives (to rounding: XLA compiles the two differently),
    including a traced field that differs between the methods (each method a learning rate of
    its own, as the swing-up preset tunes them), and it is traced once for all three. The two
    guided methods are compared with their own programs (each a compile; gp_pg's branch is the
    part both of them run, and its own program is test_sweep.py's)."""
    base = C.preset("tiny", method="gp_pg")
    priors = _tiny_priors()
    traces = []
    shared = T.make_gp_methods_train(base)

    def counted(state, index, cfg):
        traces.append(1)  # runs only while tracing
        return shared(state, index, cfg, 4)

    program = jax.jit(functools.partial(jax.lax.map, lambda a: counted(*a)))
    per_seed = lambda x: np.broadcast_to(np.asarray(x), (2,) + np.shape(x))  # noqa: E731
    rates = {"guided_variance": 0.01, "guided_direction": 0.005}
    runs = {}
    for method, rate in rates.items():
        i = PAPER_GP.index(method)
        cfg = C.preset("tiny", method=method, learning_rate=rate)
        train = T.make_train(cfg)
        state = jax.jit(jax.vmap(functools.partial(train.init, cfg=cfg)))(KEYS, prior=priors)
        # the seeds one after another (lax.map), as the shared program runs them: faster to compile
        own = jax.jit(functools.partial(jax.lax.map, functools.partial(
            train.run_chunk, cfg=cfg, num_updates=4)))(state)
        got = program((state, per_seed(np.int32(i)),
                       jax.tree_util.tree_map(per_seed, T.gp_methods_key(cfg))))
        _assert_same_run_to_rounding(got, own)
        assert np.asarray(own[1].num_basis_vectors).max() > 0
        runs[method] = cfg, state, own
    assert len(traces) == 1
    # the learning rate is read from the argument: another value gives another run
    cfg, state, own = runs["guided_variance"]
    other = program((state, per_seed(np.int32(1)),
                     jax.tree_util.tree_map(per_seed, T.gp_methods_key(cfg.replace(learning_rate=0.5)))))
    assert _max_rel_diff(other[0].theta, own[0].theta) > 1e-3
    with pytest.raises(AssertionError):
        _assert_same_run_to_rounding(other, own)
    # and the method from the index: guided_variance's config with gp_pg's index is another run
    gp_pg_like = program((state, per_seed(np.int32(0)),
                          jax.tree_util.tree_map(per_seed, T.gp_methods_key(cfg))))
    assert _max_rel_diff(gp_pg_like[0].theta, own[0].theta) > 1e-3


def test_gp_methods_program_refuses_reinforce_and_other_static_fields():
    with pytest.raises(ValueError, match="reinforce"):
        T.make_gp_methods_train(C.preset("tiny", method="reinforce"))
    shared = T.make_gp_methods_train(C.preset("tiny", method="gp_pg"))
    cfg = C.preset("tiny", method="guided_direction", num_candidates=8)
    with pytest.raises(ValueError, match="static fields"):  # before the state is looked at
        shared(None, 2, T.gp_methods_key(cfg), 1)


@pytest.mark.training
def test_a_method_alone_equals_it_among_the_others(tmp_path):
    """`reproduce` runs its GP methods through one shared program, whichever of them it is asked
    for, so a method's records are the same bit for bit alone and with the others, and compiled
    once for all of them (that the shared program agrees with each method's own to rounding:
    test_gp_methods_program_runs_each_method_as_its_own_program). A second run in the process
    reuses the first's jitted hyperparameter fit."""
    kw = dict(REPRODUCE_KW, progress=lambda m: None)
    R._SHARED_PROGRAMS.clear()
    R._FIT_PROGRAMS.clear()
    R.reproduce(out_dir=str(tmp_path / "all"), methods=list(PAPER_GP), **kw)
    assert len(R._SHARED_PROGRAMS) == 1  # one program, one chunk length
    (program,) = R._SHARED_PROGRAMS.values()
    assert program._cache_size() == 1  # compiled once, for the three methods
    R.reproduce(out_dir=str(tmp_path / "alone"), methods=["guided_variance"], **kw)
    # the second run (another directory: no kernels_<method>.npz) fits with the first run's program
    assert len(R._FIT_PROGRAMS) == 1 and next(iter(R._FIT_PROGRAMS.values()))._cache_size() == 1
    every, alone = (np.load(tmp_path / d / "results.npz") for d in ("all", "alone"))
    assert list(every["methods"]) == list(PAPER_GP)
    for k in T.RECORD_FIELDS:
        np.testing.assert_array_equal(alone[k][0], every[k][1], err_msg=k)
    with pytest.raises(ValueError, match="gp_program"):
        R.reproduce(out_dir=str(tmp_path / "bad"), methods=["gp_pg"], gp_program="union", **kw)
