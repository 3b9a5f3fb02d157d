"""The documentation: README.md and the site's pages under docs/.

Every measured number in them sits in a generated block that equals what its result file gives;
the README's quick start runs as printed; every relative link and image points to a file; the
README stays short; no page reads like a lab notebook. (The site itself is built by `make docs`,
not here.)
"""

import csv
import glob
import math
import os
import re
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT, experiment, fast_compile_env

docs_tables = experiment("docs_tables")

README = os.path.join(ROOT, "README.md")
PAGES = sorted(glob.glob(os.path.join(ROOT, "docs", "*.md")))
DOCUMENTS = [README] + PAGES
# Words about how the work was organised, or citations of a specification outside the repository
# (the bracketed letters keep this file from matching itself).
DIARY = re.compile(r"\b(this|last|next|earlier|later|previous) st[o]p\b|\bst[o]p \d+\b"
                   r"|\bsessi[o]n \d+\b|\bscr[a]tch\b|\biss[u]e \d+\b|SP[E]C §", re.I)
# Every tracked text file but the changelog (history belongs there) and the result data.
TEXT_FILES = sorted(
    p for p in subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True).stdout.split()
    if p.endswith((".py", ".md", ".toml", ".cfg", ".txt", ".yml", ".yaml", ".cff")) or p == "Makefile"
    if p != "CHANGELOG.md" and not p.startswith("docs/results/"))
# The sections of docs/design.md that the code cites as docs/design.md#<anchor>.
DESIGN_ANCHORS = ("pendulum", "gp-model", "sparse-gp", "policies", "estimators", "exploration",
                  "algorithm-1", "methods", "critic", "model",
                  "tasks", "presets", "deviations", "decisions")


def _read(path):
    with open(path, encoding="utf-8") as f:
        return f.read()


def _rel(path):
    return os.path.relpath(path, ROOT)


def test_the_documents_are_the_ones_the_generator_rewrites():
    assert docs_tables.documents() == DOCUMENTS


@pytest.mark.parametrize("path", DOCUMENTS, ids=_rel)
def test_every_generated_block_matches_its_files(path):
    text = _read(path)
    found = docs_tables.blocks(text)
    for name, body in docs_tables.blocks(docs_tables.render(text)).items():
        assert found[name] == body, (f"{_rel(path)}: block {name!r} is stale: run "
                                     "python experiments/docs_tables.py --write")


def test_every_generator_has_a_block():
    used = set()
    for path in DOCUMENTS:
        used |= set(docs_tables.blocks(_read(path)))
    assert used == set(docs_tables.TABLES), sorted(used ^ set(docs_tables.TABLES))


@pytest.mark.parametrize("path", [os.path.join(ROOT, "docs", "results.md")], ids=_rel)
def test_fig5_numbers_equal_the_summary_file_independently(path):
    """Parse the Fig. 5 rows back into numbers and compare them with summary.csv at the precision
    shown (a check that does not reuse the table generator's formatting code)."""
    body = docs_tables.blocks(_read(path))["fig5"]
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


@pytest.mark.parametrize("task", ["pendulum-v1", "mountaincar-continuous", "inverted-pendulum",
                                  "inverted-double-pendulum"])
def test_the_exploration_schemes_tuning_scores_equal_the_record_independently(task):
    """Parse the standard task's tuning table on the exploration page back into numbers and
    compare them with the record: every method and scheme tried, '–' where it was not, and the
    choice the best of the method's scores."""
    import json

    block = f"exploration_{task.replace('-', '_').replace('mountaincar_continuous', 'mountaincar')}"
    body = docs_tables.blocks(_read(os.path.join(ROOT, "docs", "exploration.md")))[block]
    with open(os.path.join(ROOT, "docs", "results", "exploration", task,
                           "standard_tuning.json")) as f:
        record = json.load(f)["methods"]
    lines = body.split("\n| method | white |", 1)[1].split("\n\n", 1)[0].splitlines()
    schemes = ["white"] + [c.strip() for c in lines[0].split("|")[:-2]]
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
            for line in lines[2:]}
    assert set(rows) == set(record)
    for method, cells in rows.items():
        score = {t["scheme"]: t["score"] for t in record[method]["tried"]}
        assert len(cells) == len(schemes) + 1
        for scheme, cell in zip(schemes, cells):
            assert cell == "–" if scheme not in score else float(cell) == round(score[scheme], 1)
        best = max(score, key=score.get)
        assert cells[-1] == record[method]["chosen"] == best, (method, cells[-1], best)


def test_the_explored_critic_rows_equal_the_records_independently():
    """Each task's gp_critic row in the standard tasks' exploration table is its run under the
    scheme its tuning record chose, with that run's summary at the precision shown; the paper's
    row is the highest final return of its methods' chosen runs; SAC's seeds count those with a
    step to the threshold."""
    import json

    body = docs_tables.blocks(_read(os.path.join(ROOT, "docs", "standard_tasks.md")))[
        "standard_critic_explored"]
    rows = [[c.strip() for c in line.split("|")[1:-1]] for line in body.splitlines()
            if line.startswith("| ") and not line.startswith("| task")]
    tasks = sorted({r[0] for r in rows})
    assert tasks == ["inverted-double-pendulum", "inverted-pendulum", "mountaincar-continuous",
                     "pendulum-v1"]
    for task in tasks:
        base = os.path.join(ROOT, "docs", "results")
        with open(os.path.join(base, "exploration", task, "standard.json")) as f:
            runs = json.load(f)["runs"]
        with open(os.path.join(base, "exploration", task, "standard_tuning.json")) as f:
            chosen = {m: r["chosen"] for m, r in json.load(f)["methods"].items()}
        with open(os.path.join(base, "standard", task, "heldout_table.json")) as f:
            sac = next(r for r in json.load(f)["rows"] if r["method"] == "sac")
        mine = {r[1]: r for r in rows if r[0] == task}
        assert mine["gp_critic"][2] == chosen["gp_critic"]
        summary = runs[f"gp_critic/{chosen['gp_critic']}"]["summary"]
        iqm = float(mine["gp_critic"][3].split(" [")[0])
        assert iqm == round(float(summary["final_return_iqm"]), 1)
        assert mine["gp_critic"][4] == f"{summary['seeds_reaching_threshold']}/10"
        paper = {m: float(runs[f"{m}/{c}"]["summary"]["final_return_iqm"])
                 for m, c in chosen.items() if m != "gp_critic" and f"{m}/{c}" in runs}
        (best,) = set(mine) - {"gp_critic", "ppo", "sac"}
        assert best == max(paper, key=paper.get) and mine[best][2] == chosen[best]
        reached = sum(s is not None for s in sac["steps_to_threshold"])
        assert mine["sac"][4] == f"{reached}/10"


@pytest.mark.parametrize("task", ["pendulum-v1", "mountaincar-continuous", "inverted-pendulum",
                                  "inverted-double-pendulum"])
def test_the_exploration_runs_steps_per_seed_agree_with_their_summaries(task):
    """The steps per seed that the exploration study's standard stage records (from the curves)
    agree with the run's own summary (written by `reproduce`): as many seeds reach the threshold,
    with the same median over them."""
    import json
    import statistics

    with open(os.path.join(ROOT, "docs", "results", "exploration", task, "standard.json")) as f:
        runs = json.load(f)["runs"]
    for key, run in runs.items():
        reached = [s for s in run["steps_to_threshold"] if s is not None]
        assert len(run["steps_to_threshold"]) == 10
        assert len(reached) == int(run["summary"]["seeds_reaching_threshold"]), key
        if reached:
            assert statistics.median(reached) == pytest.approx(
                float(run["summary"]["steps_to_threshold_median"]), rel=1e-12), key


def _quick_start(index):
    """The `index`-th ```python block of the README's Quick start section."""
    section = _read(README).split("## Quick start", 1)[1].split("\n## ", 1)[0]
    found = re.findall(r"```python\n(.*?)```", section, re.S)
    assert len(found) == 2, "the Quick start has two ```python blocks"
    return found[index]


def _run_as_printed(code, tmp_path, env, timeout):
    """`code` in a fresh process with the repository on the path, JAX's 64-bit mode off (the
    script's own choice); returns its stdout's lines after checking that it exits 0."""
    script = tmp_path / "quick_start.py"
    script.write_text(code)
    env = dict(env, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("JAX_ENABLE_X64", None)
    proc = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout.splitlines()


@pytest.mark.cli
def test_the_readme_quick_start_learns_pendulum_v1_as_printed(tmp_path):
    """gp_model on Pendulum-v1, executed exactly as printed, compiled as a user's run is (at XLA's
    level 0 gp_model's update runs many times slower, and its numbers differ): one line per
    update, the environment steps in steps of one 200-step episode, the initial controller below
    the threshold of -200 and a later one at or above it."""
    lines = _run_as_printed(_quick_start(0), tmp_path, dict(os.environ), timeout=600)
    parsed = [re.fullmatch(r"after +(\d+) environment steps: evaluation return +(-?\d+\.\d)", line)
              for line in lines]
    assert len(lines) == 6 and all(parsed), lines
    steps = [int(m.group(1)) for m in parsed]
    returns = [float(m.group(2)) for m in parsed]
    assert steps == [200 * u for u in range(6)], steps
    assert returns[0] < -200.0 and max(returns[1:]) >= -200.0, returns


@pytest.mark.cli
def test_the_readme_quick_start_of_the_paper_methods_runs_as_printed(tmp_path):
    """The second block, executed exactly as printed (compiled fast, as the other end-to-end
    tests: `conftest.fast_compile_env`)."""
    lines = _run_as_printed(_quick_start(1), tmp_path, fast_compile_env(), timeout=300)
    assert len(lines) == 2, lines
    rewards = re.findall(r"-?\d+\.\d+", lines[0])
    assert lines[0].startswith("reward per step, first update:") and len(rewards) == 4, lines[0]
    m = re.fullmatch(r"(\d+) basis vectors; at x_0 = 0\.5: mean (-?[\d.]+) \(sin 0\.5 = 0\.479\), "
                     r"variance ([\d.]+)", lines[1])
    assert m, lines[1]
    assert 1 <= int(m.group(1)) <= 20
    assert abs(float(m.group(2)) - 0.479) < 0.1 and float(m.group(3)) < 0.1  # the GP fits sin


_LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
_FENCE = re.compile(r"^```.*?^```", re.S | re.M)


@pytest.mark.parametrize("path", DOCUMENTS, ids=_rel)
def test_every_relative_link_and_image_points_to_a_file(path):
    text = _FENCE.sub("", _read(path))
    text = re.sub(r"`[^`\n]*`", "", text)
    targets = _LINK.findall(text)
    missing = []
    for target in targets:
        if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL, or an anchor on the same page
        file = target.split("#", 1)[0]
        if not os.path.exists(os.path.join(os.path.dirname(path), file)):
            missing.append(target)
    assert not missing, f"{_rel(path)}: {missing}"


def test_the_readme_is_short_and_narrow():
    lines = _read(README).splitlines()
    assert len(lines) <= 300
    wide = [i + 1 for i, line in enumerate(lines) if len(line) > 200]
    assert not wide, f"README.md lines over 200 characters: {wide}"


def _nav_pages(nav):
    """The Markdown files of mkdocs.yml's nav, in order (sections flattened)."""
    for entry in nav:
        for value in (entry.values() if isinstance(entry, dict) else [entry]):
            if isinstance(value, list):
                yield from _nav_pages(value)
            else:
                yield value


def _linked_pages(text, prefix=""):
    """The documentation pages (docs/*.md and below) that `text` links to, as paths relative to
    docs/; `prefix` is the links' path to docs/ ('docs/' from the README)."""
    text = _FENCE.sub("", text)
    pages = set()
    for target in _LINK.findall(text):
        file = target.split("#", 1)[0]
        if file.endswith(".md") and file.startswith(prefix) and not re.match(r"[a-z]+:", file):
            pages.add(file[len(prefix):])
    return pages


def test_the_readme_the_home_page_and_the_nav_list_the_same_pages():
    """Every page of the site is in mkdocs.yml's nav; the README links to each of them (the home
    page among them), and the home page to each of the others."""
    import yaml

    with open(os.path.join(ROOT, "mkdocs.yml")) as f:
        # mkdocs.yml's own tags (none today) would need mkdocs' loader; the nav is plain YAML
        nav = list(_nav_pages(yaml.safe_load(f)["nav"]))
    assert len(nav) == len(set(nav)), nav
    on_disk = {os.path.relpath(p, os.path.join(ROOT, "docs"))
               for p in glob.glob(os.path.join(ROOT, "docs", "*.md"))
               + glob.glob(os.path.join(ROOT, "docs", "notebooks", "*.md"))}
    assert set(nav) == on_disk, sorted(set(nav) ^ on_disk)
    readme = _linked_pages(_read(README), "docs/")
    home = _linked_pages(_read(os.path.join(ROOT, "docs", "index.md")))
    assert readme == set(nav), sorted(readme ^ set(nav))
    assert home == set(nav) - {"index.md"}, sorted(home ^ (set(nav) - {"index.md"}))


def test_the_headline_table_equals_the_studies_files_independently():
    """The README's headline, parsed back: per task, gp_model's cell is its study's held-out row
    under the use of the uncertainty its preset runs (`model_based.method.PRESETS`); SAC's, PPO's
    and the paper's best method's cells give the steps to the threshold and the seeds reaching it
    that the standard tasks' and the swing-up studies' own files give (medians over the seeds that
    reach it)."""
    import json
    import statistics

    from gpguided_jax.model_based.method import PRESETS

    body = docs_tables.blocks(_read(README))["headline"]
    rows = [[c.strip() for c in line.split("|")[1:-1]] for line in body.splitlines()
            if line.startswith("| ") and not line.startswith("| task")]
    assert [r[0] for r in rows] == list(docs_tables.HEADLINE_TASKS.values())
    base = os.path.join(ROOT, "docs", "results")

    def cell(steps, seeds):
        reached = [s for s in steps if s is not None and math.isfinite(s)]
        median = f"{statistics.median(reached) / 1000:.1f}k" if reached else "–"
        return median, f"{len(reached)}/{seeds}"

    def shown(text):
        m = re.fullmatch(r"(?:\w+: )?(\S+) of \S+, (\d+/\d+)", text)
        assert m, text
        return m.group(1), m.group(2)

    for task, row in zip(docs_tables.HEADLINE_TASKS, rows):
        with open(os.path.join(base, "model", task, "heldout_table.json")) as f:
            table = json.load(f)
        model = {r["method"]: r for r in table["rows"]}
        mine = model[f"gp_model ({PRESETS[task]['model_exploration']})"]
        expected = cell(mine["steps_to_threshold"], mine["seeds"])
        planned = os.path.join(base, "planning", task, "heldout", "chosen.npz")
        cheapest = os.path.join(base, "planning", task, "heldout", "cheapest.npz")
        planned = cheapest if os.path.exists(cheapest) else planned
        if os.path.exists(planned):  # the preset holds the planning study's choice (its cost
            # stage's where it ran): its runs, each seed's first evaluation at or above the
            # threshold from the raw curves
            with np.load(planned) as f:
                steps, curves = f["steps"], np.asarray(f["measure"], float)
            first = [next((int(s) for s, v in zip(steps, c) if v >= table["threshold"]), None)
                     for c in curves]
            expected = cell(first, len(curves))
        assert shown(row[2]) == expected, (task, row[2])
        paper = row[3].split(":", 1)[0]
        if task == "swingup":
            with open(os.path.join(base, "swingup", "heldout_table.json")) as f:
                others = {r["method"]: (r["steps_to_90"], r["seeds"]) for r in json.load(f)}
        else:
            with open(os.path.join(base, "standard", task, "heldout_table.json")) as f:
                others = {r["method"]: (r["steps_to_threshold"], r["seeds"])
                          for r in json.load(f)["rows"]}
        for name, text in ((paper, row[3]), ("sac", row[4]), ("ppo", row[5])):
            assert shown(text) == cell(*others[name]), (task, name, text)


def test_no_file_speaks_of_how_the_work_was_organised():
    assert len(TEXT_FILES) > 50  # git lists the repository's files
    found = {p: [m.group(0) for m in DIARY.finditer(_read(os.path.join(ROOT, p)))] for p in TEXT_FILES}
    found = {p: words for p, words in found.items() if words}
    assert not found, found


def test_the_design_page_has_the_anchors_the_code_cites():
    headings = re.findall(r"^## .*\{#([\w-]+)\}\s*$", _read(os.path.join(ROOT, "docs", "design.md")), re.M)
    assert list(DESIGN_ANCHORS) == headings
