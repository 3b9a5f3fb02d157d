"""Every number in the README's result tables equals the committed result file it names."""

import csv
import importlib.util
import json
import math
import os
import re

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
spec = importlib.util.spec_from_file_location(
    "readme_tables", os.path.join(ROOT, "experiments", "readme_tables.py"))
readme_tables = importlib.util.module_from_spec(spec)
spec.loader.exec_module(readme_tables)


def _readme():
    with open(os.path.join(ROOT, "README.md")) as f:
        return f.read()


def test_every_generated_block_matches_its_files():
    text = _readme()
    found = readme_tables.blocks(text)
    assert set(found) == set(readme_tables.TABLES), sorted(found)
    for name, body in readme_tables.blocks(readme_tables.render(text)).items():
        assert found[name] == body, f"README block {name!r} is stale: run readme_tables.py --write"


def test_fig5_numbers_equal_the_summary_file_independently():
    """Parse the README's Fig. 5 rows back into numbers and compare with summary.csv at the
    precision shown (a check that does not reuse the table generator's formatting code)."""
    body = readme_tables.blocks(_readme())["fig5"]
    rows = [line for line in body.splitlines() if line.startswith("| ") and not line.startswith("| method")]
    with open(os.path.join(ROOT, "docs", "results", "paper_float64", "summary.csv")) as f:
        summary = {r["method"]: r for r in csv.DictReader(f)}
    assert len(rows) == len(summary) == 4
    keys = ["final_iqm", "iqm_ci95_low", "iqm_ci95_high", "final_mean", "ci95_low", "ci95_high",
            "initial_mean", "updates_to_90pct"]
    for line in rows:
        method = line.split("|")[1].strip()
        numbers = [float(x) for x in re.findall(r"-?\d+\.?\d*", line.split("|", 2)[2])]
        assert len(numbers) == len(keys), line
        for key, shown in zip(keys, numbers):
            digits = 0 if key == "updates_to_90pct" else 3
            assert shown == round(float(summary[method][key]), digits), (method, key, shown)


def test_benchmark_prose_quotes_the_result_files():
    """The figures the benchmark prose repeats (outside the generated tables) equal
    bench_2026-12-02.json (the run the bullets discuss) and scaling.json at the precision shown."""
    import json

    text = _readme()
    with open(os.path.join(ROOT, "docs", "results", "bench_2026-12-02.json")) as f:
        bench = json.load(f)
    with open(os.path.join(ROOT, "docs", "results", "scaling", "scaling.json")) as f:
        scaling = {r["seeds"]: r for r in json.load(f)["results"]}
    pr, t = bench["paper_run"], bench["train"]

    def one(pattern):
        found = re.findall(pattern, text)
        assert found, pattern
        return found

    cold, warm = one(r"Whole paper run: ([\d.]+) s with an empty compile cache, ([\d.]+) s")[0]
    assert float(cold) == round(pr["cold_s"]["median"], 1)
    assert float(warm) == round(pr["warm_s"]["median"], 1)
    ratio = one(r"gp_pg: ([\d.]+)× the per-seed NumPy loop")[0]
    assert float(ratio) == round(t["numpy_gp_pg"]["ratio_jax_over_numpy"], 1)
    assert float(one(r"update alone is ([\d.]+)× NumPy")[0]) == round(bench["gp"]["ratio"], 1)
    fit, alt = one(r"Hyperparameter fit: ([\d.]+) s with the default[^,]*, ([\d.]+) s with L-BFGS")[0]
    assert float(fit) == round(t["hyperfit"]["run_s"]["median"], 2)  # next to its 3 s target
    assert float(alt) == round(t["hyperfit_alternative"]["run_s"]["median"], 2)
    big = one(r"300 seeds take ([\d,]+) s\s+instead of")[0]
    assert int(big.replace(",", "")) == round(scaling[300]["whole_paper_run_s"])
    fit300, per_seed = one(r"\((\d+) s, about ([\d.]+) s per seed")[0]
    assert int(fit300) == round(scaling[300]["hyperfit_run_s"])
    assert float(per_seed) == round(scaling[300]["hyperfit_run_s"] / 300, 1)
    with open(os.path.join(ROOT, "docs", "results", "hyperfit.json")) as f:
        fits = json.load(f)["fits"]
    a300, a40, worst = one(r"100 steps on 300 pairs: ([\d.]+) s; 40 steps on\s+500 pairs: ([\d.]+) s\)"
                           r"[\s\S]*?\(worst ([\d.]+) for both;")[0]
    assert float(a300) == round(fits["adam_300_pairs"]["run_s_median"], 1)
    assert float(a40) == round(fits["adam_40_steps"]["run_s_median"], 1)
    for name in ("adam_300_pairs", "adam_40_steps"):
        assert float(worst) == round(fits[name]["minus_default_all"]["max"], 3)
        assert not fits[name]["minus_default_all"]["within_tolerance"]
    with open(os.path.join(ROOT, "docs", "results", "seed_loop.json")) as f:
        loop = json.load(f)
    batch, alone, any_pct, one_pct = one(
        r"([\d.]+) µs per seed and point as a\s+batch of 10, ([\d.]+) µs one seed after another"
        r"[\s\S]*?at (\d+)% of the steps for 10 seeds; a single seed\s+needs it at ([\d.]+)%")[0]
    assert float(batch) == round(loop["vmap"]["us_per_seed_and_point"], 1)
    assert float(alone) == round(loop["map"]["us_per_seed_and_point"], 1)
    assert int(any_pct) == round(100 * loop["any_seed_joins_fraction"])
    assert float(one_pct) == round(100 * loop["joins_fraction_one_seed"], 1)


def test_cross_machine_figures_quote_their_files():
    """The known-limitations figures: three float64 runs (previous host, new host with OpenBLAS's
    default threads, new host with one LAPACK thread: the results before the blocked-inverse fit
    and the batched fixed-noise roll-outs of 2026-12-02, kept in onethread_2026-12-02)."""
    import csv

    text = _readme()
    runs = [{r["method"]: r for r in csv.DictReader(open(
        os.path.join(ROOT, "docs", "results", d, "summary.csv")))}
        for d in ("previous_host", "rerun_2026-12-01", "onethread_2026-12-02")]
    num = r"(-[\d.]+)"
    m = re.search(rf"final IQM\s+is {num}, {num} and {num}, its mean {num}, {num} and {num}, and "
                  r"(\d+), (\d+) and (\d+) seeds\s+end below the zero-torque policy", text)
    assert m, "cross-machine bullet not found"
    g = m.groups()
    gd = [run["guided_direction"] for run in runs]
    assert [float(x) for x in g[0:3]] == [round(float(r["final_iqm"]), 4) for r in gd]
    assert [float(x) for x in g[3:6]] == [round(float(r["final_mean"]), 3) for r in gd]
    assert [int(x) for x in g[6:9]] == [int(r["fail_below_zero_torque"]) for r in gd]
    for run in runs[1:]:
        assert run["reinforce"] == runs[0]["reinforce"]
        for name in ("gp_pg", "guided_variance"):
            assert abs(float(run[name]["final_mean"]) - float(runs[0][name]["final_mean"])) < 1e-11
    # the fourth run: the same machine, the code of the blocked-inverse fit (before the padding)
    fourth = {r["method"]: r for r in csv.DictReader(open(
        os.path.join(ROOT, "docs", "results", "unpadded_2026-12-02", "paper_float64_summary.csv")))}
    assert fourth["reinforce"]["final_mean"] == runs[2]["reinforce"]["final_mean"]
    for name in ("gp_pg", "guided_variance"):
        assert abs(float(fourth[name]["final_mean"]) - float(runs[2][name]["final_mean"])) < 1e-13
    m = re.search(rf"guided_direction's final IQM is\s+{num} with (\d+) seeds below the zero-torque",
                  text)
    assert m, "fourth-run sentence not found"
    assert float(m.group(1)) == round(float(fourth["guided_direction"]["final_iqm"]), 4)
    assert int(m.group(2)) == int(fourth["guided_direction"]["fail_below_zero_torque"])
    # the fifth run: the padded GP buffers, one program per method, against the fourth run
    now = {r["method"]: r for r in csv.DictReader(open(
        os.path.join(ROOT, "docs", "results", "per_method_2026-12-02", "paper_float64_summary.csv")))}
    m = re.search(rf"against the fourth, reinforce the same to the last digit, gp_pg and "
                  rf"guided_variance\s+within ([\d.e-]+), and guided_direction's final IQM is "
                  rf"{num} with (\d+) seeds below the zero-torque\s+policy", text)
    assert m, "fifth-run sentence not found"
    assert now["reinforce"]["final_mean"] == fourth["reinforce"]["final_mean"]
    for name in ("gp_pg", "guided_variance"):
        assert abs(float(now[name]["final_mean"]) - float(fourth[name]["final_mean"])) < float(m.group(1))
    assert float(m.group(2)) == round(float(now["guided_direction"]["final_iqm"]), 4)
    assert int(m.group(3)) == int(now["guided_direction"]["fail_below_zero_torque"])
    # the current results (the GP methods as one program) against the fifth run
    current = {r["method"]: r for r in csv.DictReader(open(
        os.path.join(ROOT, "docs", "results", "paper_float64", "summary.csv")))}
    m = re.search(rf"against the fifth, .*?reinforce and guided_variance\s+the same to the last "
                  rf"digit, gp_pg within ([\d.e-]+), and guided_direction's final IQM\s+is {num} "
                  rf"with (\d+) seeds below the zero-torque policy", text, re.S)
    assert m, "current-code sentence not found"
    for name in ("reinforce", "guided_variance"):
        assert current[name]["final_mean"] == now[name]["final_mean"], name
    gap = abs(float(current["gp_pg"]["final_mean"]) - float(now["gp_pg"]["final_mean"]))
    assert 0 < gap < float(m.group(1))
    assert float(m.group(2)) == round(float(current["guided_direction"]["final_iqm"]), 4)
    assert int(m.group(3)) == int(current["guided_direction"]["fail_below_zero_torque"])
    now = fourth  # the second machine ran the fourth run's code
    # the same code on the machine that replaced this one (make results, both dtypes)
    second = os.path.join(ROOT, "docs", "results", "second_machine_2026-12-02")
    other = {r["method"]: r for r in csv.DictReader(open(
        os.path.join(second, "paper_float64_summary.csv")))}
    m = re.search(rf"reinforce the same to the last digit, gp_pg\s+and guided_variance within "
                  rf"([\d.e-]+), guided_direction's final IQM {num} with (\d+) seeds below the\s+"
                  r"zero-torque policy, and float32 and float64 still agree within their intervals",
                  text)
    assert m, "second-machine sentence not found"
    assert other["reinforce"]["final_mean"] == now["reinforce"]["final_mean"]
    for name in ("gp_pg", "guided_variance"):
        assert abs(float(other[name]["final_mean"]) - float(now[name]["final_mean"])) < float(m.group(1))
    assert float(m.group(2)) == round(float(other["guided_direction"]["final_iqm"]), 4)
    assert int(m.group(3)) == int(other["guided_direction"]["fail_below_zero_torque"])
    with open(os.path.join(second, "consistency.json")) as f:
        cons = json.load(f)
    assert all(r["intervals_overlap"] for r in cons["f32_vs_f64"].values())
    assert len(cons["f32_vs_f64"]) == 4


def _num(text: str) -> float:
    return float(text.replace("−", "-"))


def test_sweep_figures_quote_their_csv_files():
    """The Sweeps section's β table and λ range equal docs/figures/sweep_*.csv (rounded as shown)."""
    text = _readme()
    fig = os.path.join(ROOT, "docs", "figures")
    beta = list(csv.DictReader(open(os.path.join(fig, "sweep_inverse_temperature.csv"))))
    rows = re.findall(r"^\| (\d+) \| (−[\d.]+) \| \[(−[\d.]+), (−[\d.]+)\] \|$", text, re.M)
    assert [int(r[0]) for r in rows] == [int(float(b["inverse_temperature"])) for b in beta]
    for (_, final, lo, hi), b in zip(rows, beta):
        assert _num(final) == round(float(b["final_mean"]), 3)
        assert (_num(lo), _num(hi)) == (round(float(b["ci95_low"]), 3), round(float(b["ci95_high"]), 3))
    lam = list(csv.DictReader(open(os.path.join(fig, "sweep_age_penalty.csv"))))
    m = re.search(r"no measurable effect; final (−[\d.]+) to (−[\d.]+) \[(−[\d.]+), (−[\d.]+)\] for\s+"
                  r"every λ", text)
    assert m, "λ sweep sentence not found"
    finals = sorted(round(float(r["final_mean"]), 4) for r in lam)
    assert (_num(m.group(2)), _num(m.group(1))) == (finals[0], finals[-1])
    assert {round(float(r["ci95_low"]), 3) for r in lam} == {_num(m.group(3))}
    assert {round(float(r["ci95_high"]), 3) for r in lam} == {_num(m.group(4))}


def test_profile_prose_quotes_the_profile_files():
    """The per-update times, shares and FLOP rates the profile prose repeats equal profile.json
    (map, the CPU default) and profile_vmap.json (one batch) at the precision shown."""
    import json

    text = _readme()
    res = os.path.join(ROOT, "docs", "results")
    prof = {k: json.load(open(os.path.join(res, f)))["methods"]
            for k, f in (("map", "profile.json"), ("vmap", "profile_vmap.json"))}
    m = re.search(r"One update for 10 seeds takes ([\d.]+) ms instead of ([\d.]+) ms as one batch "
                  r"\(gp_pg\), ([\d.]+) instead of\s+([\d.]+) ms \(guided_variance\) and ([\d.]+) "
                  r"instead of ([\d.]+) ms \(guided_direction\)", text)
    assert m, "profile sentence not found"
    got = [float(x) for x in m.groups()]
    want = [round(prof[loop][meth]["per_update_ms"], 1)
            for meth in ("gp_pg", "guided_variance", "guided_direction") for loop in ("map", "vmap")]
    assert got == want

    def share(meth, part):
        p = prof["map"][meth]
        if part == "policy_gp":
            return round(100 * p["rollout_policy_s"] / p["full_update_s"])
        return round(100 * p[part] / p["full_update_s"])

    m = re.search(r"gp_pg's largest part \((\d+)%\)[\s\S]*?is about as large \((\d+)%\s+and (\d+)%\)", text)
    assert m, "shares sentence not found"
    assert int(m.group(1)) == share("gp_pg", "gp_update_s")
    assert int(m.group(2)) == share("guided_variance", "policy_gp")
    assert int(m.group(3)) == share("guided_direction", "policy_gp")
    m = re.search(r"The GP update achieves ([\d.]+)–([\d.]+) GFLOP/s[\s\S]*?against ([\d.]+)–([\d.]+) "
                  r"GFLOP/s as one batch", text)
    assert m, "FLOP rate sentence not found"
    for loop, lo, hi in (("map", m.group(1), m.group(2)), ("vmap", m.group(3), m.group(4))):
        rates = [prof[loop][k]["gp_update_achieved_gflops_per_s"]
                 for k in ("gp_pg", "guided_variance", "guided_direction")]
        assert (float(lo), float(hi)) == (round(min(rates), 1), round(max(rates), 1))
    with open(os.path.join(res, "bench_2026-12-02.json")) as f:
        ratio = json.load(f)["train"]["numpy_gp_pg"]["ratio_jax_over_numpy"]
    m = re.search(r"which gives the ([\d.]+)×, not 20×", text)
    assert m and float(m.group(1)) == round(ratio, 1)


def test_scaling_rerun_figures_quote_their_file():
    """The 2026-12-01 seed-scaling re-run's figures equal its scaling.json."""
    import json

    text = _readme()
    with open(os.path.join(ROOT, "docs", "results", "scaling_2026-12-01", "scaling.json")) as f:
        new = {r["seeds"]: r for r in json.load(f)["results"]}
    m = re.search(r"gp_pg\s+([\d,]+)–([\d,]+) seeds·updates/s from 10 to 300 seeds, in a slow hour\) and "
                  r"the peak memory under 1 GiB\s+\(([\d.]+) GiB at 300 seeds\)", text)
    assert m, "scaling re-run paragraph not found"
    rates = [r["methods"]["gp_pg"]["seed_updates_per_s"] for r in new.values()]
    assert sorted(new) == [10, 30, 100, 300]
    assert int(m.group(1).replace(",", "")) == round(min(rates))
    assert int(m.group(2).replace(",", "")) == round(max(rates))
    assert float(m.group(3)) == round(new[300]["peak_rss_bytes"] / 2**30, 2)
    assert all(r["peak_rss_bytes"] < 2**30 for r in new.values())


def test_gp_step_and_compile_cache_prose_quote_their_files():
    """The GP-step bound (gp_step.json) and the compilation-cache check (compile_cache.json) as
    the benchmark prose repeats them, at the precision shown."""
    import json

    text = " ".join(_readme().split())
    res = os.path.join(ROOT, "docs", "results")
    step = json.load(open(os.path.join(res, "gp_step.json")))
    m = re.search(r"a projected pair costs ([\d.]+) µs in the segmented loop, .*? take ([\d.]+) µs on "
                  r"their own \(([\d.]+) µs in float32.*?Launching one small operation costs ([\d.]+) µs"
                  r".*? costs ([\d.]+)–([\d.]+) µs per pair in isolation", text)
    assert m, "GP-step sentence not found"
    blocks = sorted(round(step["block"][b]["us_per_pair"], 1) for b in ("25", "50"))
    assert [float(x) for x in m.groups()] == [
        round(step["real_us_per_pair"], 1), round(step["four_passes_us"]["float64"], 1),
        round(step["four_passes_us"]["float32"], 1), round(step["small_op_us"], 2), *blocks]
    assert max(b["max_cov_alpha_difference"] for b in step["block"].values()) <= 2e-16

    cache = json.load(open(os.path.join(res, "compile_cache.json")))
    m = re.search(r"all (\d+) chunk programs \(2 presets × 4 methods, (\d+)–(\d+) kernels\) load "
                  r"\(by JAX's count of programs loaded from the cache, .*?\), and so "
                  r"does a synthetic program of (\d+) unrolled steps \((\d+) kernels\), but one of (\d+) "
                  r"steps \((\d+) kernels\) crashes", text)
    assert m, "compilation-cache sentence not found"
    progs = cache["programs"]
    assert all(p["loads"] and p["warm"]["cache_hits"] > 0 for p in progs)
    assert int(m.group(1)) == len(progs)
    kernels = [p["cold"]["kernels"] for p in progs]
    assert [int(m.group(2)), int(m.group(3))] == [min(kernels), max(kernels)]
    synth = {s["steps"]: s for s in cache["synthetic"]}
    ok, bad = synth[int(m.group(4))], synth[int(m.group(6))]
    assert ok["loads"] and ok["cold"]["kernels"] == int(m.group(5))
    assert not bad["loads"] and bad["warm"]["returncode"] != 0 and bad["cold"]["kernels"] == int(m.group(7))


def test_lapack_threads_prose_quotes_its_file():
    """The Benchmarks paragraph on LAPACK threads equals docs/results/lapack_threads.json."""
    text = _readme()
    with open(os.path.join(ROOT, "docs", "results", "lapack_threads.json")) as f:
        lt = json.load(f)
    m = re.search(r"in fresh processes, the two settings in turn: ([\d.]+) s with OpenBLAS's default, "
                  r"([\d.]+) s with one\s+thread \(([\d.]+)×\)", text)
    assert m, "LAPACK threads paragraph not found"
    default, one, ratio = map(float, m.groups())
    assert default == round(lt["settings"]["default"]["fit_s"]["median"], 1)
    assert one == round(lt["settings"]["one_thread"]["fit_s"]["median"], 1)
    assert ratio == round(lt["default_over_one_thread"], 1)
    assert lt["settings"]["one_thread"]["same_bits_in_every_trial"]
    assert lt["settings"]["default"]["same_bits_in_every_trial"]
    assert not lt["same_bits_across_settings"]


def test_failing_seed_prose_quotes_the_summary_files():
    """The sentence under the failures table equals both dtypes' summary files."""
    import csv

    text = _readme()
    rows = {dt: {r["method"]: r for r in csv.DictReader(open(
        os.path.join(ROOT, "docs", "results", f"paper_{dt}", "summary.csv")))}
        for dt in ("float64", "float32")}
    m = re.search(r"REINFORCE in (\d+) of 100 seeds \(in both dtypes\), guided_direction\s+in (\d+) in "
                  r"float64 and (\d+) in float32", text)
    assert m, "failing-seed sentence not found"
    rf, gd64, gd32 = map(int, m.groups())
    for dt in rows:
        assert rf == int(rows[dt]["reinforce"]["failing_seeds"])
    assert gd64 == int(rows["float64"]["guided_direction"]["failing_seeds"])
    assert gd32 == int(rows["float32"]["guided_direction"]["failing_seeds"])
    for dt in rows:
        for name in ("gp_pg", "guided_variance"):
            assert int(rows[dt][name]["failing_seeds"]) == 0


def test_benchmark_comparison_with_the_previous_run_quotes_both_files():
    """The targets' comparison with the benchmark run before this stop's changes equals
    bench_2026-12-02_before.json (and its side, bench_2026-12-02.json)."""
    text = _readme()
    res = os.path.join(ROOT, "docs", "results")
    with open(os.path.join(res, "bench_2026-12-02_before.json")) as f:
        old = json.load(f)
    with open(os.path.join(res, "bench_2026-12-02.json")) as f:
        new = json.load(f)
    m = re.search(r"`docs/results/bench_2026-12-02_before.json`\): ([\d.]+) s and ([\d.]+) s", text)
    assert m, "previous paper-run sentence not found"
    assert float(m.group(1)) == round(old["paper_run"]["cold_s"]["median"], 1)
    assert float(m.group(2)) == round(old["paper_run"]["warm_s"]["median"], 1)
    m = re.search(r"It was ([\d.]+) s in the report before", text)
    assert m and float(m.group(1)) == round(old["train"]["hyperfit"]["run_s"]["median"], 1)
    m = re.search(r"gp_pg's\s+run took ([\d.]+) s against ([\d.]+) s in the report before, but the NumPy "
                  r"loop also ran faster this\s+hour \(([\d.]+) ms per update against ([\d.]+) ms\)", text)
    assert m, "NumPy-loop comparison not found"

    def per_update(b):  # ms
        return b["train"]["numpy_gp_pg"]["seconds_per_update_one_seed"] * 1e3

    def gp_run(b):
        return b["train"]["methods"]["gp_pg"]["run_s"]["median"]

    assert [float(x) for x in m.groups()] == [round(gp_run(new), 2), round(gp_run(old), 2),
                                             round(per_update(new), 1), round(per_update(old), 1)]
    new_ratio = new["train"]["numpy_gp_pg"]["ratio_jax_over_numpy"]
    assert f"missed by {20 / new_ratio:.2f}× in this run" in text
    pr = new["paper_run"]
    assert f"missed by {pr['cold_s']['median'] - 30:.1f} s with an empty one" in text
    assert pr["warm_s"]["median"] < 30


def test_fast_paths_prose_quotes_its_files():
    """This stop's changes as the Benchmarks prose states them: fast_paths.json (the in-turn
    comparisons) and hyperfit.json (the fit's likelihood against the 2026-11-23 report)."""
    text = " ".join(_readme().split())
    res = os.path.join(ROOT, "docs", "results")
    fast = json.load(open(os.path.join(res, "fast_paths.json")))
    fit = fast["fit"]
    m = re.search(r"the 10-seed fit took ([\d.]+) s against ([\d.]+) s \(([\d.]+)×\), the fitted "
                  r"hyperparameters differ by at most ([\d.e-]+) relative", text)
    assert m, "fit sentence not found"
    assert [float(x) for x in m.groups()[:3]] == [
        round(fit["blocked"]["run_s_median"], 2), round(fit["plain"]["run_s_median"], 2),
        round(fit["speedup_blocked_over_plain"], 2)]
    assert float(m.group(4)) == float(f"{fit['max_relative_difference_of_fitted_hyperparameters']:.1e}")
    assert f"{fit['speedup_blocked_over_plain']:.2f}× faster in turn" in text
    roll = fast["rollouts"]
    m = re.search(r"REINFORCE's run ([\d.]+)× and gp_pg's ([\d.]+)× faster", text)
    assert m and [float(x) for x in m.groups()] == [
        round(roll["reinforce"]["speedup_side_by_side"], 2), round(roll["gp_pg"]["speedup_side_by_side"], 2)]
    assert f"gp_pg's run {roll['gp_pg']['speedup_side_by_side']:.2f}× faster (below)" in text
    ref = json.load(open(os.path.join(res, "hyperfit.json")))["adam_minus_reference_all"]
    m = re.search(r"every seed's NLML per pair is within ([\d.e-]+) nats of the fit before", text)
    assert m and float(m.group(1)) == float(f"{ref['max_abs']:.1e}") and ref["within_tolerance"]


def test_second_machine_prose_quotes_its_file():
    """The Benchmarks paragraph on the second machine: its figures are those of
    bench_2026-12-02_second_machine.json (and bench_2026-12-02.json for the first), as rounded there."""
    text = " ".join(_readme().split())
    res = os.path.join(ROOT, "docs", "results")
    with open(os.path.join(res, "bench_2026-12-02.json")) as f:
        first = json.load(f)
    with open(os.path.join(res, "bench_2026-12-02_second_machine.json")) as f:
        second = json.load(f)

    def figures(b):
        t = b["train"]
        return {"gp_pg": round(t["methods"]["gp_pg"]["run_s"]["median"], 2),
                "fit": round(t["hyperfit"]["run_s"]["median"], 2),
                "ms": round(1e3 * t["numpy_gp_pg"]["seconds_per_update_one_seed"], 1),
                "ratio": round(t["numpy_gp_pg"]["ratio_jax_over_numpy"], 1),
                "compile": round(sum(m["compile_s"] for m in t["methods"].values()), 1),
                "cold": round(b["paper_run"]["cold_s"]["median"], 1),
                "warm": round(b["paper_run"]["warm_s"]["median"], 1)}

    a, b = figures(first), figures(second)
    miss = round(100 * (b["fit"] / 3 - 1))
    sentence = (f"(gp_pg's run {b['gp_pg']:.2f} s against {a['gp_pg']:.2f} s, the fit {b['fit']:.2f} s "
                f"against {a['fit']:.2f} s) and the interpreted NumPy loop faster ({b['ms']:.1f} ms per "
                f"update against {a['ms']:.1f} ms), so gp_pg's ratio falls to {b['ratio']:.1f}× and the "
                f"fit misses its target by {miss}%; it compiles faster ({b['compile']:.1f} s for the four "
                f"methods against {a['compile']:.1f} s), so the whole run is {b['cold']:.1f} s cold and "
                f"{b['warm']:.1f} s warm")
    assert sentence in text, sentence
    assert b["warm"] < 30 and a["warm"] < 30
    assert (f"the warm run is {b['warm']:.1f} s, the cold one {b['cold']:.1f} s, the ratio "
            f"{b['ratio']:.1f}× and the fit {b['fit']:.2f} s") in text


def test_shorter_adam_fit_prose_quotes_its_files():
    """The Benchmarks sentence on the 50-step Adam fit: its schedule keeps the tolerance on every
    tuning seed (schedules.json), and the paper-run figures are those of adam50_fit's summaries
    and of the default fit's run on the same machine."""
    import csv

    text = " ".join(_readme().split())
    res = os.path.join(ROOT, "docs", "results")
    with open(os.path.join(res, "adam50_fit", "schedules.json")) as f:
        sched = json.load(f)
    (row,) = [r for r in sched["schedules"] if (r["steps"], r["learning_rate"]) == (50, 0.15)]
    assert row["seeds_better"] == len(sched["seeds"]) and row["within_tolerance"]

    def gd(path):
        rows = {r["method"]: r for r in csv.DictReader(open(os.path.join(res, path)))}
        return rows["guided_direction"]

    short64, short32 = gd("adam50_fit/paper_float64_summary.csv"), gd("adam50_fit/paper_float32_summary.csv")
    default64 = gd("second_machine_2026-12-02/paper_float64_summary.csv")
    sentence = (f"a float64 final IQM of {float(short64['final_iqm']):.4f} with "
                f"{short64['failing_seeds']} failing seeds against {float(default64['final_iqm']):.4f} "
                f"with {default64['failing_seeds']} for the default fit on the same machine, and "
                f"{short32['failing_seeds']} failing seeds in float32")
    assert sentence in text, sentence


def _results_json(name: str) -> dict:
    """A JSON file under docs/results/."""
    with open(os.path.join(ROOT, "docs", "results", name)) as f:
        return json.load(f)


def test_slot_padding_prose_quotes_its_file():
    """The sparse-GP section's figures for the padded buffers are those of slot_padding.json, and
    the module's notes quote the same rounded ratios."""
    text = " ".join(_readme().split())
    pad = _results_json("slot_padding.json")
    f64 = pad["gp_update"]["float64"]["padded_over_unpadded"]
    f32 = pad["gp_update"]["float32"]["padded_over_unpadded"]
    gp_pg = pad["train"]["float64"]["gp_pg"]["padded_over_unpadded"]
    sentence = (f"The GP update alone is {f64:.2f}× the time in float64 and {f32:.2f}× in float32, "
                f"gp_pg's paper run {gp_pg:.2f}×")
    assert sentence in text, sentence
    assert all(g["same_basis_vectors"] for g in pad["gp_update"].values())
    assert pad["slot_multiple"] == {"unpadded": 1, "padded": 8}
    with open(os.path.join(ROOT, "gpguided_jax", "sparse_gp.py")) as f:
        notes = " ".join(f.read().split())
    assert (f"the GP update alone is about {round(100 * (1 - f64))}% faster in float64 and "
            f"{round(100 * (1 - f32))}% in float32") in notes


def test_third_machine_prose_quotes_its_files():
    """The Benchmarks paragraph on the third machine: its figures are those of
    bench_2026-12-02_third_machine.json and bench_2026-12-02.json, and the estimate without the padding is
    the quotient it claims (slot_padding.json)."""
    text = " ".join(_readme().split())
    third = _results_json("bench_2026-12-02_third_machine.json")
    first = _results_json("bench_2026-12-02.json")
    pad = _results_json("slot_padding.json")
    t = third["train"]
    ratio = t["numpy_gp_pg"]["ratio_jax_over_numpy"]
    run = t["methods"]["gp_pg"]["run_s"]["median"]
    factor = pad["train"]["float64"]["gp_pg"]["padded_over_unpadded"]
    cold, warm = third["paper_run"]["cold_s"]["median"], third["paper_run"]["warm_s"]["median"]
    sentence = (f"gp_pg's ratio is {ratio:.1f}×, over its target, and the GP update alone "
                f"{third['gp']['ratio']:.1f}×; the whole run is {cold:.1f} s "
                f"cold and {warm:.1f} s warm, and the fit takes "
                f"{t['hyperfit']['run_s']['median']:.2f} s. Only the ratio meets its target there.")
    assert sentence in text, sentence
    assert ratio >= 20 and third["paper_run"]["cold_s"]["median"] >= 30
    assert t["hyperfit"]["run_s"]["median"] > 3 and third["paper_run"]["warm_s"]["median"] >= 30
    ms = (f"the NumPy loop took {1e3 * t['numpy_gp_pg']['seconds_per_update_one_seed']:.1f} ms per "
          f"update against {1e3 * first['train']['numpy_gp_pg']['seconds_per_update_one_seed']:.1f} ms "
          f"on the first machine")
    assert ms in text, ms
    unpadded = run / factor
    without = (f"about {run:.2f} s / {factor:.3f} = {unpadded:.2f} s, a ratio of about "
               f"{t['numpy_gp_pg']['extrapolated_run_s'] / unpadded:.1f}×")
    assert without in text, without
    n = t["numpy_gp_pg"]["seconds_per_update"]
    fastest = n["min"] * t["numpy_gp_pg"]["extrapolated_run_s"] / n["median"] / run
    spread = (f"The NumPy loop's three runs there took {1e3 * n['min']:.1f}–{1e3 * n['max']:.1f} ms per "
              f"update; at its fastest the ratio would be {fastest:.1f}×")
    assert spread in text, spread


def test_status_quotes_the_third_machine():
    text = " ".join(_readme().split())
    b = _results_json("bench_2026-12-02_third_machine.json")
    pad = _results_json("slot_padding.json")
    speedup = 1 / pad["train"]["float64"]["gp_pg"]["padded_over_unpadded"]
    n = b["train"]["numpy_gp_pg"]
    fastest = (n["seconds_per_update"]["min"] * n["extrapolated_run_s"] / n["seconds_per_update"]["median"]
               / b["train"]["methods"]["gp_pg"]["run_s"]["median"])
    sentence = (f"(about {speedup:.2f}× faster for gp_pg), the ratio is "
                f"{b['train']['numpy_gp_pg']['ratio_jax_over_numpy']:.1f}× (met, by the median of a "
                f"noisy NumPy loop: {fastest:.1f}× at its fastest run), the cold run "
                f"{b['paper_run']['cold_s']['median']:.1f} s, the warm one "
                f"{b['paper_run']['warm_s']['median']:.1f} s and the fit "
                f"{b['train']['hyperfit']['run_s']['median']:.2f} s (missed)")
    assert sentence in text, sentence


def test_the_avx2_machines_sentence_quotes_its_bench_file():
    """The Status paragraph's figures of the AMD Zen 3 (AVX2) stop equal its bench report."""
    text = " ".join(_readme().split())
    b = _results_json("bench_2026-12-03_zen3.json")
    t, pr = b["train"], b["paper_run"]
    m = re.search(r"bench_2026-12-03_zen3\.json`, this stop's code\): the cold run "
                  r"([\d.]+) s, the warm one ([\d.]+) s, the fit ([\d.]+) s \(all missed\) and the ratio "
                  r"([\d.]+)× \(met, because the NumPy loop runs slower there: ([\d.]+) ms per update "
                  r"against gp_pg's run of ([\d.]+) s\), with the shared program compiled in ([\d.]+) s "
                  r"against ([\d.]+) s for three", text)
    assert m, "Zen 3 sentence not found"
    own3 = sum(t["methods"][k]["compile_s"] for k in ("gp_pg", "guided_variance", "guided_direction"))
    fit = t["hyperfit"]["run_s"]["median"]
    assert [float(x) for x in m.groups()] == [
        round(pr["cold_s"]["median"], 1), round(pr["warm_s"]["median"], 1), round(fit, 2),
        round(t["numpy_gp_pg"]["ratio_jax_over_numpy"], 1),
        round(1e3 * t["numpy_gp_pg"]["seconds_per_update_one_seed"], 1),
        round(t["methods"]["gp_pg"]["run_s"]["median"], 2),
        round(t["gp_methods_program"]["compile_s"], 1), round(own3, 1)]
    assert pr["warm_s"]["median"] > 30 and fit > 3 and t["numpy_gp_pg"]["ratio_jax_over_numpy"] >= 20


def test_the_second_zen4_sentence_quotes_its_bench_file():
    """The Status paragraph's figures of the last stop of 2026-12-03 equal its bench report,
    and its split of the cold command adds up (in-process compile + compute, then the rest)."""
    text = " ".join(_readme().split())
    b = _results_json("bench_2026-12-03_zen4_second.json")
    t, pr = b["train"], b["paper_run"]
    m = re.search(r"bench_2026-12-03_zen4_second\.json`\): the cold run ([\d.]+) s, the warm one "
                  r"([\d.]+) s, the fit ([\d.]+) s and the ratio ([\d.]+)× \(all missed\)\. In the "
                  r"same report the fit, the compilation and the runs take ([\d.]+) s in one process: "
                  r"([\d.]+) s compiling \(the fit, REINFORCE's program and the GP methods' one "
                  r"program\) and ([\d.]+) s computing \(the fit and the four runs\)\. The ([\d.]+) s "
                  r"left of the cold command .*? Computation and those alone take ([\d.]+) s", text)
    assert m, "second Zen 4 sentence not found"
    fit = t["hyperfit"]
    shared = t["gp_methods_program"]
    compile_s = fit["compile_s"] + t["methods"]["reinforce"]["compile_s"] + shared["compile_s"]
    compute_s = fit["run_s"]["median"] + t["methods"]["reinforce"]["run_s"]["median"] + sum(
        r["run_s"]["median"] for r in shared["methods"].values())
    cold = pr["cold_s"]["median"]
    rest = cold - t["in_process_total_s"]
    assert math.isclose(compile_s + compute_s, t["in_process_total_s"], rel_tol=1e-9)
    assert [float(x) for x in m.groups()] == [
        round(cold, 1), round(pr["warm_s"]["median"], 1), round(fit["run_s"]["median"], 2),
        round(t["numpy_gp_pg"]["ratio_jax_over_numpy"], 1), round(t["in_process_total_s"], 1),
        round(compile_s, 1), round(compute_s, 1), round(rest, 1), round(compute_s + rest, 1)]
    assert cold > 30 and fit["run_s"]["median"] > 3 and t["numpy_gp_pg"]["ratio_jax_over_numpy"] < 20
    assert compute_s + rest >= 29.95  # the claim: computation and the rest alone reach 30 s


def test_this_stops_benchmark_prose_quotes_bench_json():
    """The figures of the 2026-12-03 benchmark paragraph (the GP methods as one program) equal
    bench.json, bench_2026-12-02.json for the first machine's, and compile_cache_gp_methods.json
    for the shared program's size, at the precision shown."""
    text = " ".join(_readme().split())
    b, first = _results_json("bench.json"), _results_json("bench_2026-12-02.json")
    t, pr = b["train"], b["paper_run"]
    own3 = sum(t["methods"][k]["compile_s"] for k in ("gp_pg", "guided_variance", "guided_direction"))
    m = re.search(r"gp_pg's run ([\d.]+) s against ([\d.]+) s, the fit ([\d.]+) s against ([\d.]+) s\)", text)
    assert m, "machine sentence not found"
    assert [float(x) for x in m.groups()] == [
        round(t["methods"]["gp_pg"]["run_s"]["median"], 2),
        round(first["train"]["methods"]["gp_pg"]["run_s"]["median"], 2),
        round(t["hyperfit"]["run_s"]["median"], 2), round(first["train"]["hyperfit"]["run_s"]["median"], 2)]
    m = re.search(r"The whole paper run: ([\d.]+) s with an empty compile cache, ([\d.]+) s with a warm "
                  r"one\*\* \(target < 30 s: met warm, \*\*missed cold by ([\d.]+) s\*\*\)\. .*? take "
                  r"([\d.]+) s in one process against ([\d.]+) s with one program per method: the shared "
                  r"program compiles in ([\d.]+) s instead of ([\d.]+) s\. The other ([\d.]+) s", text)
    assert m, "paper-run bullet not found"
    cold, warm = pr["cold_s"]["median"], pr["warm_s"]["median"]
    assert [float(x) for x in m.groups()] == [
        round(cold, 1), round(warm, 1), round(cold - 30, 1), round(t["in_process_total_s"], 1),
        round(t["in_process_total_per_method_s"], 1), round(t["gp_methods_program"]["compile_s"], 1),
        round(own3, 1), round(cold - t["in_process_total_s"], 1)]
    assert warm < 30 < cold
    m = re.search(r"gp_pg runs ([\d.]+)× as fast as the per-seed NumPy loop\*\* .*? \(([\d.]+) ms per "
                  r"update against ([\d.]+) ms\) and gp_pg's run slower \(([\d.]+) s\)\. The GP update "
                  r"alone is ([\d.]+)× its NumPy reference here \(([\d.]+)× on the first machine\): the "
                  r"reference ran ([\d.]+)× faster than there and the JAX program ([\d.]+)× slower", text)
    assert m, "ratio bullet not found"
    n, g, g1 = t["numpy_gp_pg"], b["gp"], first["gp"]
    assert [float(x) for x in m.groups()] == [
        round(n["ratio_jax_over_numpy"], 1), round(1e3 * n["seconds_per_update_one_seed"], 1),
        round(1e3 * first["train"]["numpy_gp_pg"]["seconds_per_update_one_seed"], 1),
        round(t["methods"]["gp_pg"]["run_s"]["median"], 2), round(g["ratio"], 1), round(g1["ratio"], 1),
        round(g["numpy_updates_per_s"] / g1["numpy_updates_per_s"], 2),
        round(g1["jax_updates_per_s"] / g["jax_updates_per_s"], 2)]
    m = re.search(r"The hyperparameter fit takes ([\d.]+) s\*\* with the default, ([\d.]+) s with L-BFGS "
                  r"\(target ≤ 3 s: \*\*missed by the default by ([\d.]+) s", text)
    assert m, "fit bullet not found"
    fit = t["hyperfit"]["run_s"]["median"]
    assert [float(x) for x in m.groups()] == [
        round(fit, 2), round(t["hyperfit_alternative"]["run_s"]["median"], 2), round(fit - 3, 2)]
    g = t["gp_methods_program"]
    m = re.search(r"compiles in ([\d.]+) s against ([\d.]+) s for the three programs it replaces "
                  r"\(a run of one GP method alone compiles it too: ([\d.]+) s against "
                  r"([\d.]+)–([\d.]+) s", text)
    own = [t["methods"][k]["compile_s"] for k in ("gp_pg", "guided_variance", "guided_direction")]
    assert m and [float(x) for x in m.groups()] == [
        round(g["compile_s"], 1), round(own3, 1), round(g["compile_s"], 1), round(min(own), 1),
        round(max(own), 1)]
    cache = {p["preset"]: p for p in _results_json("compile_cache_gp_methods.json")["programs"]}
    m = re.search(r"(\d+) kernels for the paper preset and (\d+) for the swing-up preset, and both load",
                  text)
    assert m and [int(x) for x in m.groups()] == [cache["paper"]["cold"]["kernels"],
                                                  cache["swingup"]["cold"]["kernels"]]
    assert all(p["loads"] and p["method"] == "gp_methods" for p in cache.values())


def test_gp_program_prose_quotes_its_file():
    """The shared-vs-own program comparison as the compilation paragraph repeats it equals
    gp_program.json."""
    text = " ".join(_readme().split())
    d = _results_json("gp_program.json")["methods"]
    m = re.search(r"gp_pg's run takes ([\d.]+)× its own program's time, guided_variance's ([\d.]+)× "
                  r"\(slower in each pair\) and guided_direction's ([\d.]+)×; ([\d.]+) s against ([\d.]+) s "
                  r"for the three\. .*? are the same both ways, guided_variance's floats too, bit for bit, "
                  r"and gp_pg's and guided_direction's agree within a relative ([\d.e-]+) and ([\d.e-]+)\.",
                  text)
    assert m, "shared-program sentence not found"
    g = m.groups()
    assert [float(x) for x in g[:3]] == [round(d[k]["shared_over_own_run"], 3)
                                         for k in ("gp_pg", "guided_variance", "guided_direction")]
    gv = d["guided_variance"]
    assert all(a > b for a, b in zip(gv["shared_run_s"]["runs"], gv["own_run_s"]["runs"]))
    assert float(g[3]) == round(sum(r["shared_run_s"]["median"] for r in d.values()), 1)
    assert float(g[4]) == round(sum(r["own_run_s"]["median"] for r in d.values()), 1)
    assert all(r["integer_records_equal"] for r in d.values()) and gv["max_rel_diff"] == 0.0
    assert float(g[5]) == float(f"{d['gp_pg']['max_rel_diff']:.0e}")
    assert float(g[6]) == float(f"{d['guided_direction']['max_rel_diff']:.0e}")
