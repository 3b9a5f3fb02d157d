"""The two test tiers (tests/conftest.py): `make test` runs -m "not slow", `make test-all` and CI
every test. A marker missing from pyproject.toml, a kind of long test that is not `slow`, or a
Makefile or CI that runs the other tier would put tests in the wrong tier without a word."""

import os
import re
import subprocess
import sys

from conftest import LONG_KINDS, ROOT


def _read(name):
    with open(os.path.join(ROOT, name), encoding="utf-8") as f:
        return f.read()


def _recipe(makefile, target):
    """The command lines of `target`'s recipe, joined."""
    match = re.search(rf"^{re.escape(target)}:[^\n]*\n((?:\t[^\n]*\n)+)", makefile, re.M)
    assert match, f"no recipe for {target} in the Makefile"
    return " ".join(line.strip() for line in match.group(1).splitlines())


def test_every_marker_is_registered_and_every_kind_of_long_test_is_slow(request):
    """pyproject.toml registers `slow` and the kinds of `LONG_KINDS`, and nothing else of ours;
    every marker of a collected test is registered, and a test of a kind is `slow` as well (in
    the fast tier, such a test would be here without it)."""
    block = re.search(r"^markers = \[\n(.*?)^\]", _read("pyproject.toml"), re.S | re.M)
    assert block, "no markers list in pyproject.toml"
    assert re.findall(r'^\s*"(\w+):', block.group(1), re.M) == ["slow", *LONG_KINDS]
    registered = {line.split(":", 1)[0].split("(", 1)[0].strip()
                  for line in request.config.getini("markers")}
    items = request.session.items
    assert request.node in items
    for item in items:
        names = {mark.name for mark in item.iter_markers()}
        assert names <= registered, (item.nodeid, sorted(names - registered))
        assert not names & set(LONG_KINDS) or "slow" in names, item.nodeid


def test_a_misspelt_marker_fails_the_collection(tmp_path):
    """Under the project's pytest settings (--strict-markers), a test marked `slwo` is an error;
    beside it, a test marked `slow` collects."""
    (tmp_path / "test_typo.py").write_text("import pytest\n\n\n@pytest.mark.slwo\ndef test_a():\n"
                                           "    pass\n")
    (tmp_path / "test_fine.py").write_text("import pytest\n\n\n@pytest.mark.slow\ndef test_b():\n"
                                           "    pass\n")
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
         "-c", os.path.join(ROOT, "pyproject.toml"), "--rootdir", str(tmp_path), str(tmp_path)],
        cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode != 0, proc.stdout
    assert "'slwo' not found in `markers` configuration option" in proc.stdout, proc.stdout
    assert "test_fine.py::test_b" in proc.stdout, proc.stdout


def test_make_test_runs_the_fast_tier_and_ci_runs_every_test():
    """`make test` is `make test-all` with -m "not slow" and nothing else changed, and .ci/run
    runs `make test-all`, not `make test`."""
    makefile = _read("Makefile")
    fast, every = _recipe(makefile, "test"), _recipe(makefile, "test-all")
    assert ' -m "not slow" ' in fast
    assert fast.replace(' -m "not slow"', "", 1) == every
    assert "slow" not in every
    assert re.search(r"^\.PHONY:.* test-all\b", makefile, re.M)
    ci = [line.strip() for line in _read(".ci/run").splitlines()]
    assert "make test-all" in ci and "make test" not in ci
