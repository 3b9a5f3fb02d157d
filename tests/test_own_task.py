"""docs/own_task.md, "Your own task": its code runs as printed, and what it says the errors are is
what they are.

The page's ```python block that starts with ``# my_tasks.py`` is the task's module: it is written
to a temporary directory as my_tasks.py. The page's other ```python blocks run in order in one
fresh process in that directory (as one would paste them), and each ```text block that follows
one of them is what that block prints. Its ```bash block runs there too, with `gpguided` as
``python -m gpguided_jax.cli``. Beside them, `gpguided reproduce --import` is checked on its own:
a module that is not there, and a module whose task is refused, each end the command in one line.
"""

import json
import os
import re
import shlex
import subprocess
import sys

import pytest
from conftest import ROOT, fast_compile_env

PAGE = os.path.join(ROOT, "docs", "own_task.md")
_BLOCK = re.compile(r"^```(\w+)\n(.*?)^```$", re.S | re.M)
MARK = "=== block {} ==="


def _blocks():
    with open(PAGE, encoding="utf-8") as f:
        return [(lang, body) for lang, body in _BLOCK.findall(f.read())]


def _env():
    env = fast_compile_env(PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("JAX_ENABLE_X64", None)  # the page turns it on itself
    return env


def _cli(command: str) -> list[str]:
    """A ```bash command of the page as arguments, `gpguided` as this Python's module."""
    args = shlex.split(command.replace("\\\n", " "))
    assert args[0] == "gpguided", command
    return [sys.executable, "-m", "gpguided_jax.cli", *args[1:]]


def test_the_page_has_the_blocks_this_test_runs():
    blocks = _blocks()
    langs = [lang for lang, _ in blocks]
    assert langs.count("bash") == 1 and "text" in langs
    modules = [body for lang, body in blocks if lang == "python" and body.startswith("# my_tasks.py")]
    assert len(modules) == 1
    # every text block follows a python block (its output)
    for i, (lang, _) in enumerate(blocks):
        if lang == "text":
            assert blocks[i - 1][0] == "python", i


@pytest.mark.cli
def test_the_page_runs_as_printed(tmp_path):
    """The module, the page's Python in one process and its command line, as printed: every
    statement check finds the statement equal to the environment's steps, the runs' evaluation
    returns are finite, each error block is what its code prints, and the command writes the
    run's files and its report."""
    blocks = _blocks()
    script = []
    expected = {}  # python block index -> its text block
    for i, (lang, body) in enumerate(blocks):
        if lang == "python" and body.startswith("# my_tasks.py"):
            (tmp_path / "my_tasks.py").write_text(body)
        elif lang == "python":
            script.append(f"print({MARK.format(i)!r}, flush=True)\n{body}")
        elif lang == "text":
            expected[i - 1] = body
    (tmp_path / "page.py").write_text("\n".join(script))
    proc = subprocess.run([sys.executable, "page.py"], cwd=tmp_path, env=_env(),
                          capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]
    printed = dict(re.findall(r"=== block (\d+) ===\n(.*?)(?=^=== block |\Z)", proc.stdout,
                              re.S | re.M))
    for i, text in expected.items():
        assert printed[str(i)] == text, (i, printed[str(i)], text)
    checks = re.findall(r"^\{'reward_error': .*\}$", proc.stdout, re.M)
    assert len(checks) == 3, proc.stdout
    for line in checks:
        check = eval(line)  # a dict of numbers and None, as printed
        assert check["reward_error"] < 1e-4 and check["end_disagreements"] in (0, None), line
        assert check["steps"] > 0
    runs = re.findall(r"^(\w+) evaluation returns: \[(.*)\]$", proc.stdout, re.M)
    assert [m for m, _ in runs] == ["gp_model", "reinforce"], proc.stdout
    for _, values in runs:
        assert all(-1e4 < float(v) <= 0 for v in values.split(","))

    (command,) = [body for lang, body in blocks if lang == "bash"]
    cli = subprocess.run(_cli(command.strip()), cwd=tmp_path, env=_env(), capture_output=True,
                         text=True, timeout=1200)
    assert cli.returncode == 0, cli.stderr[-3000:]
    out = tmp_path / "results" / "cart"
    for name in ("results.npz", "summary.csv", "config.json", "index.html"):
        assert (out / name).exists(), name
    with open(out / "config.json") as f:
        assert sorted(json.load(f)["methods"]) == ["gp_model", "reinforce"]


def _one_line_error(tmp_path, *args):
    proc = subprocess.run([sys.executable, "-m", "gpguided_jax.cli", "reproduce", *args,
                           "--preset", "tiny", "--compile-cache", "none",
                           "--out", str(tmp_path / "out")],
                          cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=300)
    assert proc.returncode != 0
    lines = proc.stderr.strip().splitlines()
    assert lines and lines[-1].startswith("gpguided reproduce: error: "), proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr, proc.stderr[-2000:]
    return lines[-1]


@pytest.mark.cli
def test_an_import_that_fails_ends_the_command_in_one_line(tmp_path):
    """A module that is not there; a module whose task is refused (a reward without the end its
    task states); a module that registers a task without a reward, with gp_model asked to plan
    with the stated one. Each ends `gpguided reproduce` in one line naming the problem, before
    anything compiles."""
    line = _one_line_error(tmp_path, "--import", "no_such_module", "--env", "pendulum")
    assert "--import no_such_module: ModuleNotFoundError" in line
    cart = [body for lang, body in _blocks() if lang == "python" and body.startswith("# my_tasks")]
    (tmp_path / "my_tasks.py").write_text(cart[0])
    (tmp_path / "broken.py").write_text(
        "import my_tasks\nfrom gpguided_jax import tasks\n"
        "tasks.register(my_tasks.CART._replace(name='cart-2', reward_fn=lambda o, a, n: -o[0]))\n")
    line = _one_line_error(tmp_path, "--import", "broken", "--env", "cart-2")
    assert "--import broken: TaskError: task 'cart-2' states end_fn, so its reward_fn must take" in line
    (tmp_path / "unstated.py").write_text(
        "import my_tasks\nfrom gpguided_jax import tasks\n"
        "tasks.register(my_tasks.CART._replace(name='cart-unstated', reward_fn=None))\n")
    line = _one_line_error(tmp_path, "--import", "unstated", "--env", "cart-unstated",
                           "--methods", "gp_model", "--set", "model_reward=stated")
    assert "'stated' plans with what cart-unstated does not declare: tasks.Task.reward_fn" in line
    line = _one_line_error(tmp_path, "--env", "cart")  # a task no imported module registered
    assert "unknown environment 'cart'" in line
