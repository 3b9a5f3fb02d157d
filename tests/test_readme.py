"""Every number in the README's result tables equals the committed result file it names."""

import csv
import importlib.util
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
