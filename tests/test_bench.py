"""`gpguided bench` end to end at tiny sizes, and the benchmark table generated from its report."""

import json

import pytest
from conftest import ROOT, run_script

pytestmark = pytest.mark.cli


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

    spec = importlib.util.spec_from_file_location(
        "docs_tables", os.path.join(ROOT, "experiments", "docs_tables.py"))
    tables = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tables)
    tables.RESULTS = str(tmp_path)
    table = tables.bench_table()
    assert f"**{n['ratio_jax_over_numpy']:.1f}x**" in table
    assert "median [min, max] of 2 runs" in table
    assert f"{report['paper_run']['cold_s']['median']:.1f} s" in table
    assert f"compile {shared['compile_s']:.1f} s once for all three" in table
    assert "one update at GP budget M = 16" in table
