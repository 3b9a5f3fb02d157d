"""`gpguided bench` end to end at tiny sizes, and the benchmark table generated from its report."""

import json

import pytest
from conftest import experiment, run_script

pytestmark = pytest.mark.cli



def _docs_tables(results_dir):
    """experiments/docs_tables.py, reading its result files from `results_dir`."""
    tables = experiment("docs_tables")
    tables.RESULTS = str(results_dir)
    return tables

def test_gpguided_bench_quick_writes_the_report_the_readme_table_is_made_from(tmp_path):
    """`gpguided bench` end to end at tiny sizes (2 runs of each figure, the whole-command timing
    included): stdout and --out hold the same report, every timing is a median of its runs, the
    ratios are the quotients they claim, and the README's bench tables render from it."""
    import math

    path = tmp_path / "bench.json"
    # every section but gp_model's, which the next test runs
    proc = run_script(["-m", "gpguided_jax.cli", "bench", "--quick", "--repeats", "2", "--out", path,
                       "--sections", "env", "gp", "train", "capacity", "paper_run"])
    report = json.loads(proc.stdout)
    assert json.loads(path.read_text()) == report
    assert report["quick"] and report["repeats"] == 2
    assert "model" not in report

    def check_stats(s, runs=2):
        assert s["runs"] == runs and 0 < s["min"] <= s["median"] <= s["max"], s

    t = report["train"]
    assert list(t["methods"]) == ["reinforce", "gp_pg"]  # quick: the ratio's two sides alone
    for m in t["methods"]:
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
    cap = report["capacity"]["capacities"]
    assert list(cap) == ["16"] and list(cap["16"]) == ["gp_critic"]
    check_stats(cap["16"]["gp_critic"]["per_update_s"])
    assert report["paper_run"]["methods"] == ["reinforce"]  # quick: the cheapest whole command
    check_stats(report["paper_run"]["cold_s"], runs=1)  # the quick run times the command once
    check_stats(report["paper_run"]["warm_s"], runs=1)

    tables = _docs_tables(tmp_path)
    table = tables.bench_table()
    assert f"**{n['ratio_jax_over_numpy']:.1f}x**" in table
    assert "median [min, max] of 2 runs" in table
    assert f"{report['paper_run']['cold_s']['median']:.1f} s" in table
    assert f"compile {shared['compile_s']:.1f} s once for all three" in table
    assert "one update at GP budget M = 16" in table


MODEL_PARTS = ["episodes", "take_in", "condition_before", "refit", "condition_after", "optimise",
               "evaluation"]


def test_gp_model_section_at_tiny_sizes_merged_into_a_report(tmp_path):
    """`gpguided bench --sections model --merge` at tiny sizes: the section goes into the report
    at --out beside its other sections; each part of gp_model's update and the whole update, per
    dtype, is compiled and timed apart (positive times, medians of their runs, figures per seed
    the medians over the seeds), on the state after its warm-up updates (the buffer holds their
    transitions); the parts add up to the whole within a loose factor; the seed scaling has a
    row per seed count; and the docs' table renders from the report."""
    import math

    from gpguided_jax import bench

    path = tmp_path / "bench.json"
    path.write_text(json.dumps({"repeats": 3, "env": {"kept": True}}))
    proc = run_script(["-m", "gpguided_jax.cli", "bench", "--quick", "--repeats", "2",
                       "--sections", "model", "--merge", "--out", path])
    report = json.loads(path.read_text())
    assert json.loads(proc.stdout) == report
    assert report["env"] == {"kept": True} and report["repeats"] == 3  # the others stay as they were
    m = report["model"]
    assert m["repeats"] == 2 and m["quick"]
    assert list(m["tasks"]) == ["pendulum-v1"]  # quick: one task

    def check_stats(s, runs=2):
        assert s["runs"] == runs and 0 < s["min"] <= s["median"] <= s["max"], s

    by_dtype = m["tasks"]["pendulum-v1"]
    assert list(by_dtype) == ["float64", "float32"]
    for dtype, r in by_dtype.items():
        assert r["dtype"] == dtype and r["seeds"] == 2 and r["warm_updates"] == 1
        c = r["settings"]
        assert (c["episode_length"], c["inducing"], c["steps"], c["particles"]) == tuple(
            bench.QUICK_MODEL[k] for k in ("episode_length", "model_inducing", "model_steps",
                                           "model_particles"))
        # the warm-up update's one episode is in the buffer (Pendulum-v1 never ends early)
        assert r["buffer_transitions"] == c["episodes"] * c["episode_length"] < c["capacity"]
        assert list(r["parts"]) == MODEL_PARTS
        for t in [*r["parts"].values(), r["update"]]:
            check_stats(t["run_s"])
            assert t["compile_s"] > 0
            assert math.isclose(t["per_seed_s"], t["run_s"]["median"] / r["seeds"], rel_tol=1e-12)
        total = sum(t["run_s"]["median"] for t in r["parts"].values())
        assert math.isclose(r["parts_sum_s"], total, rel_tol=1e-12)
        assert math.isclose(r["parts_over_update"], total / r["update"]["run_s"]["median"],
                            rel_tol=1e-12)
        # each part once: their sum is about the whole (loose: the programs' dispatch and a
        # shared machine's noise weigh at these sizes)
        assert 0.25 < r["parts_over_update"] < 4, r["parts_over_update"]
        assert math.isclose(r["parts_compile_sum_s"],
                            sum(t["compile_s"] for t in r["parts"].values()), rel_tol=1e-12)
    sc = m["seed_scaling"]
    assert (sc["task"], sc["dtype"]) == ("pendulum-v1", "float64")
    assert [row["seeds"] for row in sc["rows"]] == [1, 2]  # quick: 1 and 2 seeds
    for row in sc["rows"]:
        check_stats(row["run_s"])
        assert row["compile_s"] > 0
        assert math.isclose(row["per_seed_s"], row["run_s"]["median"] / row["seeds"], rel_tol=1e-12)

    tables = _docs_tables(tmp_path)
    table = tables.bench_model_table()
    for label in tables.MODEL_PART_LABELS.values():
        assert table.count(f"| pendulum-v1 | {label} |") == 1
    whole = [tables._duration(by_dtype[d]["update"]["per_seed_s"]) for d in by_dtype]
    assert "| pendulum-v1 | **the whole update** | " + " | ".join(
        f"**{w}** | {by_dtype[d]['update']['compile_s']:.1f} s" for w, d in zip(whole, by_dtype)
    ) + " |" in table
    assert "from the state after 1 update," in " ".join(table.split())  # the caption's lines joined
