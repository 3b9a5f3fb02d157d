"""Smoke tests of the benchmark scripts at tiny sizes, so that an API change cannot rot them."""

import json

from conftest import ROOT, run_script


def _run(args, **kw):
    """The script's JSON; it compiles fast (`conftest.fast_compile_env`) unless told otherwise."""
    return json.loads(run_script(args, **kw).stdout)


def test_bench_seed_loop_prints_json():
    # level 0 alone: with XLA's older fusion emitters the two loops' posteriors differ by rounding
    out = _run(["experiments/bench_seed_loop.py", "--seeds", "3", "--points", "60", "--repeats", "1"],
               fast_compile="level0")
    assert out["vmap"]["run_s"] > 0 and out["map"]["run_s"] > 0
    # a batch runs the insertion branch at least as often as any one of its seeds needs it
    assert 0 < out["joins_fraction_one_seed"] <= out["any_seed_joins_fraction"] <= 1
    assert out["segments_equal_scan_loop_bitwise"] is True  # the two loops of update_batch


def test_bench_gp_loop_compares_the_two_loops_bitwise():
    out = _run(["experiments/bench_gp_loop.py", "--seeds", "2", "--repeats", "1",
                "--methods", "gp_pg", "--preset", "tiny"])
    row = out["methods"]["gp_pg"]
    # Bit for bit before the padded GP buffers; since them XLA compiles the two loops' surroundings
    # in the training program differently, and the records agree to rounding (~1e-11 here).
    assert row["max_abs_float_difference"] < 1e-8
    assert row["scan"]["run_s_median"] > 0 and row["segments"]["run_s_median"] > 0


def test_bench_gp_step_block_update_agrees_with_the_pair_by_pair_loop():
    out = _run(["experiments/bench_gp_step.py", "--iterations", "2", "--repeats", "1"])
    assert out["real_us_per_pair"] > 0 and out["four_passes_us"]["float64"] > 0
    for row in out["block"].values():  # the block form of Potter's update: the same posterior
        assert row["max_cov_alpha_difference"] < 1e-12 and row["max_alpha_difference"] < 1e-10


def test_compile_cache_check_round_trips_a_program():
    # the GP methods' shared program, compiled as a user's run compiles it (the cache keys on flags)
    out = _run(["experiments/compile_cache_check.py", "--presets", "tiny", "--methods", "gp_methods",
                "--synthetic", "2"], fast_compile=False)
    assert out["all_shipped_programs_load"] and out["programs"][0]["cold"]["kernels"] > 0
    assert out["synthetic"][0]["loads"]


def test_bench_fast_paths_compares_each_fast_path_with_the_one_it_replaced():
    # level 0 alone: with XLA's older fusion emitters the two roll-outs' records differed by 7.7e-6
    out = _run(["experiments/bench_fast_paths.py", "--preset", "tiny", "--seeds", "2",
                "--repeats", "1"], fast_compile="level0")
    # the blocked inverse changes the fit only by rounding
    assert out["fit"]["max_relative_difference_of_fitted_hyperparameters"] < 1e-6
    assert out["fit"]["plain"]["run_s_median"] > 0 and out["fit"]["blocked"]["run_s_median"] > 0
    for method in ("reinforce", "gp_pg"):  # the same episodes, summed in another order
        assert out["rollouts"][method]["max_abs_record_difference"] < 1e-6


def test_gpguided_bench_quick_writes_the_report_the_readme_table_is_made_from(tmp_path):
    """`gpguided bench` end to end at tiny sizes (2 runs of each figure, the whole-command timing
    included): stdout and --out hold the same report, every timing is a median of its runs, the
    ratios are the quotients they claim, and the README's bench tables render from it."""
    import importlib.util
    import math
    import os

    path = tmp_path / "bench.json"
    proc = run_script(["-m", "gpguided_jax.cli", "bench", "--quick", "--repeats", "2", "--out", path])
    report = json.loads(proc.stdout)
    assert json.loads(path.read_text()) == report
    assert report["quick"] and report["repeats"] == 2

    def check_stats(s, runs=2):
        assert s["runs"] == runs and 0 < s["min"] <= s["median"] <= s["max"], s

    t = report["train"]
    for m in ("reinforce", "gp_pg", "guided_variance", "guided_direction"):
        check_stats(t["methods"][m]["run_s"])
        assert t["methods"][m]["compile_s"] > 0
    shared = t["gp_methods_program"]  # the GP methods as reproduce runs them: one program
    assert list(shared["methods"]) == ["gp_pg", "guided_variance", "guided_direction"]
    for r in shared["methods"].values():
        check_stats(r["run_s"])
    assert shared["compile_s"] > 0
    fit = t["hyperfit"]["compile_s"] + t["hyperfit"]["run_s"]["median"]
    reinforce = t["methods"]["reinforce"]["compile_s"] + t["methods"]["reinforce"]["run_s"]["median"]
    assert math.isclose(t["in_process_total_s"], fit + reinforce + shared["compile_s"] + sum(
        r["run_s"]["median"] for r in shared["methods"].values()), rel_tol=1e-12)
    assert math.isclose(t["in_process_total_per_method_s"], fit + sum(
        r["compile_s"] + r["run_s"]["median"] for r in t["methods"].values()), rel_tol=1e-12)
    check_stats(t["hyperfit"]["run_s"])
    check_stats(t["hyperfit_alternative"]["run_s"])
    assert {t["hyperfit"]["optimizer"], t["hyperfit_alternative"]["optimizer"]} == {"adam", "lbfgs"}
    n = t["numpy_gp_pg"]
    check_stats(n["seconds_per_update"])
    assert n["seconds_per_update_one_seed"] == n["seconds_per_update"]["median"]
    gp_run = t["methods"]["gp_pg"]["run_s"]["median"]
    assert math.isclose(n["ratio_jax_over_numpy"], n["extrapolated_run_s"] / gp_run, rel_tol=1e-12)
    g = report["gp"]
    check_stats(g["jax_run_s"])
    check_stats(g["numpy_run_s"])
    assert math.isclose(g["ratio"], g["jax_updates_per_s"] / g["numpy_updates_per_s"], rel_tol=1e-12)
    for s in report["env"].values():
        check_stats(s["run_s"])
    assert report["paper_run"]["methods"] == ["reinforce"]  # quick: the cheapest whole command
    check_stats(report["paper_run"]["cold_s"], runs=1)  # the quick run times the command once
    check_stats(report["paper_run"]["warm_s"], runs=1)

    spec = importlib.util.spec_from_file_location(
        "readme_tables", os.path.join(ROOT, "experiments", "readme_tables.py"))
    tables = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tables)
    tables.RESULTS = str(tmp_path)  # bench.json and the other machines' reports, all this one
    for name in tables.MACHINE_REPORTS:
        if name != "bench.json":
            (tmp_path / name).write_text(path.read_text())
    table = tables.bench_table()
    assert f"**{n['ratio_jax_over_numpy']:.1f}x**" in table
    assert "median [min, max] of 2 runs" in table
    assert f"{report['paper_run']['cold_s']['median']:.1f} s" in table
    assert f"compile {shared['compile_s']:.1f} s once for all three" in table
    machines = tables.bench_machines_table()
    assert f"{n['ratio_jax_over_numpy']:.1f}" in machines
    shared_compile = t["methods"]["reinforce"]["compile_s"] + shared["compile_s"]
    assert f"| the same, the GP methods as one program [s] | {shared_compile:.1f} |" in machines


def test_hyperfit_adam_schedules_compares_each_schedule_with_the_default():
    out = _run(["experiments/hyperfit_adam_schedules.py", "--seeds", "1", "--schedules", "1"])
    (row,) = out["schedules"]
    assert len(row["minus_default_per_pair"]) == 1 and row["max"] == row["minus_default_per_pair"][0]
    assert row["within_tolerance"] == (row["max"] <= out["tolerance_nats_per_pair"])


def test_bench_slot_padding_compares_padded_and_unpadded_buffers():
    out = _run(["experiments/bench_slot_padding.py", "--quick"])
    for row in out["gp_update"].values():  # the same decisions either way
        assert row["same_basis_vectors"] and row["slots"] == {"unpadded": 101, "padded": 104}
        assert row["run_s"]["padded"]["median"] > 0 and row["padded_over_unpadded"] > 0
    gp_pg = out["train"]["float64"]["gp_pg"]  # the same run up to rounding
    assert gp_pg["max_abs_difference_mean_reward"] < 1e-6 and gp_pg["padded_over_unpadded"] > 0


def test_profile_host_overhead_times_what_run_method_does_between_chunks(tmp_path):
    """profile_train's host figure: the records gathered and the checkpoint written, per chunk,
    for the GP state (the checkpoint holds every leaf of it and all records so far)."""
    import importlib.util
    import os

    spec = importlib.util.spec_from_file_location(
        "profile_train", os.path.join(ROOT, "experiments", "profile_train.py"))
    prof = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(prof)
    out = prof.host_overhead([0, 1], 2, repeats=3, preset="tiny")
    assert len(out["runs_s"]) == 3 and all(t > 0 for t in out["runs_s"])
    assert out["host_s_per_chunk"] == sorted(out["runs_s"])[1]
    cfg = prof.config_lib.preset("tiny", method="gp_pg")
    state_bytes = 2 * 8 * (cfg.gp_capacity + 1) ** 2  # at least the GP's two factors, 2 seeds
    assert out["checkpoint_bytes"] > state_bytes


def test_bench_gp_program_compares_the_shared_program_with_each_methods_own():
    # compiled as a user's run compiles them (at XLA's optimisation level 0 the two programs'
    # first gradient norms differ by 3e-8 relative: gp_pg, tiny preset, checked 2026-12-03)
    out = _run(["experiments/bench_gp_program.py", "--preset", "tiny", "--seeds", "2",
                "--repeats", "1", "--methods", "guided_variance"], fast_compile=False)
    assert list(out["methods"]) == ["guided_variance"]
    assert out["shared_compile_s"] > 0
    for row in out["methods"].values():  # the same run, to rounding
        assert row["integer_records_equal"]
        assert row["max_rel_diff_first_update"] < 1e-11 and row["max_rel_diff"] < 1e-6
        assert row["shared_over_own_run"] == row["shared_run_s"]["median"] / row["own_run_s"]["median"]
