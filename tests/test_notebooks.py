"""Executes every notebook in notebooks/ at reduced size, so that a broken notebook fails CI.

The notebooks are jupytext percent-format `.py` files. Each is converted to a notebook in memory
and run top to bottom by nbclient in a fresh kernel with GPGUIDED_NOTEBOOK_QUICK=1 (the notebooks'
size knob) and the Agg matplotlib backend; any cell that raises fails the test.

The kernel is the Python running pytest: a kernelspec pointing at `sys.executable` is written to a
temporary directory and looked up there, so no `ipykernel install` is needed in a fresh environment.

At the reduced size the notebooks spend most of their time compiling, so the kernel runs XLA's CPU
backend at optimisation level 0 (`conftest.fast_compile_env`; it compiles much faster, and the
tiny runs do not notice the slower code). This is for the test only: the notebooks themselves run with
JAX's defaults.

The documentation site shows each notebook executed at full size, as a page that
experiments/render_notebooks.py writes (`make notebooks`) and the repository keeps
(docs/notebooks/); `test_the_site_shows_each_notebook_as_it_is` checks that each page shows its
notebook's current cells, without executing anything.
"""

import json
import pathlib
import re
import sys

import pytest
from conftest import fast_compile_env

jupytext = pytest.importorskip("jupytext")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")
from jupyter_client.kernelspec import KernelSpecManager  # noqa: E402
from jupyter_client.manager import KernelManager  # noqa: E402

NOTEBOOK_DIR = pathlib.Path(__file__).resolve().parent.parent / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("[0-9][0-9]_*.py"))
KERNEL_NAME = "gpguided-notebook-test"
CELL_TIMEOUT_S = 300  # generous: the tests may run in parallel on a loaded CPU


@pytest.fixture(scope="module")
def kernel_spec_manager(tmp_path_factory):
    kernels_dir = tmp_path_factory.mktemp("jupyter") / "kernels"
    spec_dir = kernels_dir / KERNEL_NAME
    spec_dir.mkdir(parents=True)
    spec = {
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "gpguided_jax notebook test",
        "language": "python",
        "env": {
            "GPGUIDED_NOTEBOOK_QUICK": "1",
            "MPLBACKEND": "Agg",
            "XLA_FLAGS": fast_compile_env()["XLA_FLAGS"],
        },
    }
    (spec_dir / "kernel.json").write_text(json.dumps(spec))
    return KernelSpecManager(kernel_dirs=[str(kernels_dir)])


def test_notebooks_exist():
    names = [p.name for p in NOTEBOOKS]
    assert names == [
        "01_pendulum_and_gp.py",
        "02_exploration_schemes.py",
        "03_autodiff_verification.py",
        "04_sweeps.py",
        "05_model_based.py",
    ]


def _renderer():
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "render_notebooks", NOTEBOOK_DIR.parent / "experiments" / "render_notebooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_the_site_shows_each_notebook_as_it_is(path):
    """docs/notebooks/<name>.md, written by experiments/render_notebooks.py with the notebook's
    outputs, shows the notebook's current cells (its outputs taken out, it is the page of the
    cells alone); every figure it links to is a file, and it shows at least one output."""
    render = _renderer()
    page_path = render.PAGES / f"{path.stem}.md"
    assert page_path.exists(), f"no page for {path.name}: run python experiments/render_notebooks.py"
    page = page_path.read_text()
    cells = render.markdown(path, render.read(path))
    assert render.strip_outputs(page) == render.strip_outputs(cells), (
        f"{page_path.name} shows an older {path.name}: run python experiments/render_notebooks.py "
        f"{path.stem}")
    figures = re.findall(r"!\[output\]\(([^)]+)\)", page)
    assert all((page_path.parent / f).exists() for f in figures), figures
    assert figures or "```text" in page
    # no figure left over from an earlier rendering
    on_disk = {p.name for p in (render.PAGES / f"{path.stem}_files").glob("*")}
    assert on_disk == {pathlib.PurePosixPath(f).name for f in figures}


@pytest.mark.notebooks
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_executes(path, kernel_spec_manager):
    nb = jupytext.read(path, fmt="py:percent")
    assert sum(c.cell_type == "code" for c in nb.cells) >= 3, "not a percent-format notebook?"
    first_code = next(c.source for c in nb.cells if c.cell_type == "code")
    assert 'QUICK = os.environ.get("GPGUIDED_NOTEBOOK_QUICK") == "1"' in first_code
    km = KernelManager(kernel_name=KERNEL_NAME, kernel_spec_manager=kernel_spec_manager)
    client = nbclient.NotebookClient(
        nb,
        km=km,
        timeout=CELL_TIMEOUT_S,
        resources={"metadata": {"path": str(NOTEBOOK_DIR)}},
    )
    client.execute()  # raises CellExecutionError, naming the cell, on any error
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert not any(o.get("output_type") == "error" for o in outputs)
