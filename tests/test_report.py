"""A run's report (`gpguided_jax.report`): index.html beside the run's files, which a browser reads
without the library: every figure by a relative link to a file beside it, the summary and
comparison tables, the config; well-formed; the same page wherever the directory is moved."""

import csv
import html.parser
import json
import shutil

import matplotlib
import numpy as np
import pytest
from conftest import REPRODUCE_KW

from gpguided_jax import report

matplotlib.use("Agg")

VOID = {"meta", "img", "br", "hr", "link", "input"}


class _Page(html.parser.HTMLParser):
    """The page's images, text and whether its tags nest."""

    def __init__(self):
        super().__init__()
        self.stack, self.images, self.text, self.errors = [], [], [], []

    def handle_starttag(self, tag, attrs):
        if tag == "img":
            self.images.append(dict(attrs)["src"])
        if tag not in VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if not self.stack or self.stack.pop() != tag:
            self.errors.append(tag)

    def handle_data(self, data):
        self.text.append(data)


def _parse(path):
    page = _Page()
    page.feed(path.read_text(encoding="utf-8"))
    page.close()
    return page


def _fake_run(out):
    """A run's files as `reproduce` writes them, two methods that differ in one field."""
    out.mkdir()
    base = {"method": "reinforce", "num_updates": 6, "learning_rate": 0.01,
            "pendulum": {"mass": 1.0, "start_mean": [0.0, 0.0]}}
    config = {"preset": "tiny", "seeds": list(range(1000, 1010)), "dtype": "float32",
              "methods": {"reinforce": base, "gp_pg": dict(base, method="gp_pg",
                                                           learning_rate=0.02)}}
    (out / "config.json").write_text(json.dumps(config))
    with open(out / "summary.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["method", "seeds", "final_mean", "failing_seeds"])
        w.writerow(["reinforce", "10", "-0.3199143721", "2"])
        w.writerow(["gp_pg", "10", "-0.2641021847", "0"])
    with open(out / "comparisons.csv", "w", newline="") as f:
        csv.writer(f).writerows([["x", "y", "p"], ["gp_pg", "reinforce", "0.91"]])
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(2, 1))
    ax.plot([0, 1], [0, 1])
    fig.savefig(out / "fig5_reward.png")
    plt.close(fig)


def test_the_report_of_a_run_reads_without_the_library(tmp_path):
    _fake_run(tmp_path / "run")
    path = report.write_report(str(tmp_path / "run"))
    assert path == str(tmp_path / "run" / "index.html")
    shutil.move(tmp_path / "run", tmp_path / "moved")  # a copy elsewhere reads the same
    page = _parse(tmp_path / "moved" / "index.html")
    assert not page.errors and not page.stack, (page.errors, page.stack)
    assert page.images == ["fig5_reward.png"]
    assert all((tmp_path / "moved" / src).exists() for src in page.images)
    text = " ".join(page.text)
    for shown in ("-0.3199", "-0.2641", "0.91", "gp_pg", "learning_rate", "0.02",
                  "10 seeds, 1000–1009", "preset tiny"):
        assert shown in text, shown
    raw = (tmp_path / "moved" / "index.html").read_text()
    assert str(tmp_path) not in raw and "http" not in raw.replace("http-equiv", "")
    # the field in which the methods differ is listed first and marked
    assert raw.index('<tr class="differs"><td>learning_rate') < raw.index("<td>num_updates")
    assert '<tr class="differs"><td>method' in raw


def test_the_report_can_be_written_for_an_earlier_run(tmp_path, capsys):
    """`python -m gpguided_jax.report RUN_DIR` (its `main`): the report of a run's files; one line
    on stderr for a directory that holds no run."""
    _fake_run(tmp_path / "run")
    assert report.main([str(tmp_path / "run")]) == 0
    assert capsys.readouterr().out.strip() == f"wrote {tmp_path / 'run' / 'index.html'}"
    assert (tmp_path / "run" / "index.html").exists()
    assert report.main([str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no config.json" in err


@pytest.mark.training
def test_reproduce_writes_the_report_beside_its_files(tmp_path):
    """A tiny `reproduce` of two methods: index.html shows both Fig. 5 panels, every method's
    summary row with its numbers and the comparison, and the config the run wrote."""
    from gpguided_jax import reproduce

    out = tmp_path / "run"
    res = reproduce.reproduce(out_dir=str(out), progress=lambda m: None,
                              **dict(REPRODUCE_KW, methods=["reinforce", "gp_pg"]))
    assert res["complete"]
    page = _parse(out / "index.html")
    assert not page.errors and not page.stack
    assert sorted(page.images) == ["fig5_exploration.png", "fig5_reward.png"]
    text = " ".join(page.text)
    for row in res["summary"]:
        assert row["method"] in text
        assert f"{float(row['final_mean']):.4g}" in text
    assert "Probability of improvement" in text
    with open(out / "config.json") as f:
        assert json.load(f)["chunk_size"] == REPRODUCE_KW["chunk_size"]
    assert np.load(out / "results.npz")["mean_reward"].shape[:2] == (2, len(REPRODUCE_KW["seeds"]))
