"""The notebooks as pages of the documentation site, with their outputs (`make notebooks`).

Each jupytext percent-format notebook `notebooks/NN_name.py` is executed top to bottom in a fresh
kernel (the Python running this script) at full size, and written as `docs/notebooks/NN_name.md`:
its Markdown cells as they are, its code cells as ```python blocks, each code cell's printed
output as a ```text block and its figures as PNG files in `docs/notebooks/NN_name_files/`. The
pages are committed, so that `make docs` only reads them (fast, and strict on their links);
`tests/test_notebooks.py` checks that each page shows its notebook's current cells (and executes
every notebook at reduced size).

Usage:
  python experiments/render_notebooks.py                    # every notebook, full size
  python experiments/render_notebooks.py 05_model_based     # one (a name's start is enough)
  python experiments/render_notebooks.py --quick --out DIR  # reduced size elsewhere (a check)
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import pathlib
import shutil
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parent.parent
NOTEBOOKS = ROOT / "notebooks"
PAGES = ROOT / "docs" / "notebooks"
KERNEL_NAME = "gpguided-render"
CELL_TIMEOUT_S = 1800


def notebooks() -> list[pathlib.Path]:
    """The notebooks, in order: notebooks/NN_*.py."""
    return sorted(NOTEBOOKS.glob("[0-9][0-9]_*.py"))


def read(path: pathlib.Path):
    import jupytext

    return jupytext.read(path, fmt="py:percent")


def _header(path: pathlib.Path) -> str:
    rel = path.relative_to(ROOT).as_posix()
    return (f"<!-- rendered from {rel} by experiments/render_notebooks.py (make notebooks); "
            "edit the notebook, not this page -->\n")


def _fence(text: str, lang: str) -> str:
    """`text` as a fenced block whose fence no line of it closes."""
    fence = "```"
    while fence in text:
        fence += "`"
    return f"{fence}{lang}\n{text.rstrip()}\n{fence}"


def _text_outputs(outputs) -> list[str]:
    """The printed text of a code cell's outputs (stdout and results; stderr left out: the
    libraries' log lines), consecutive streams joined."""
    parts, stream = [], ""
    for out in outputs:
        kind = out.get("output_type")
        if kind == "stream":
            if out.get("name") == "stdout":
                stream += out.get("text", "")
            continue
        if stream:
            parts.append(("text", stream))
            stream = ""
        data = out.get("data", {})
        if "image/png" in data:
            parts.append(("png", data["image/png"]))
        elif "text/plain" in data and kind == "execute_result":
            parts.append(("text", data["text/plain"]))
    if stream:
        parts.append(("text", stream))
    return parts


def markdown(path: pathlib.Path, nb, images: pathlib.Path | None = None) -> str:
    """The page of notebook `nb` (read from `path`): its cells and, given the directory `images`
    where its figures go, its outputs (module notes). Without `images` the page has the cells
    alone: what the test compares a rendered page with, its outputs taken out."""
    blocks = [_header(path).rstrip()]
    figure = 0
    for i, cell in enumerate(nb.cells):
        source = cell.source.strip("\n")
        if cell.cell_type == "markdown":
            blocks.append(source)
            continue
        if cell.cell_type != "code" or not source:
            continue
        blocks.append(_fence(source, "python"))
        if images is None:
            continue
        for kind, value in _text_outputs(cell.get("outputs", [])):
            if kind == "text":
                if value.strip():
                    blocks.append(_fence(value, "text"))
            else:
                figure += 1
                name = f"cell{i:02d}_{figure}.png"
                images.mkdir(parents=True, exist_ok=True)
                (images / name).write_bytes(base64.b64decode(value))
                blocks.append(f"![output]({images.name}/{name})")
    return "\n\n".join(blocks) + "\n"


def strip_outputs(page: str) -> str:
    """A rendered page with its outputs taken out (its ```text blocks and output figures), as
    `markdown` writes it without outputs."""
    import re

    page = re.sub(r"\n\n(`{3,})text\n.*?\n\1(?=\n)", "", page, flags=re.S)
    return re.sub(r"\n\n!\[output\]\([^)]*\)(?=\n)", "", page)


def _kernel_manager(tmp: pathlib.Path, quick: bool):
    from jupyter_client.kernelspec import KernelSpecManager
    from jupyter_client.manager import KernelManager

    spec_dir = tmp / "kernels" / KERNEL_NAME
    spec_dir.mkdir(parents=True)
    env = {"GPGUIDED_NOTEBOOK_QUICK": "1" if quick else "0", "PYTHONPATH": str(ROOT)}
    spec = {"argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}",
                     "--InlineBackend.rc={'figure.dpi': 110}"],
            "display_name": "gpguided_jax render", "language": "python", "env": env}
    (spec_dir / "kernel.json").write_text(json.dumps(spec))
    ksm = KernelSpecManager(kernel_dirs=[str(tmp / "kernels")])
    return KernelManager(kernel_name=KERNEL_NAME, kernel_spec_manager=ksm)


def render(path: pathlib.Path, out_dir: pathlib.Path, quick: bool = False) -> pathlib.Path:
    """Executes the notebook at `path` and writes its page (and figures) to `out_dir`."""
    import nbclient

    nb = read(path)
    os.environ.pop("MPLBACKEND", None)  # the kernel's figures inline, not to a file backend
    with tempfile.TemporaryDirectory() as tmp:
        client = nbclient.NotebookClient(nb, km=_kernel_manager(pathlib.Path(tmp), quick),
                                         timeout=CELL_TIMEOUT_S,
                                         resources={"metadata": {"path": str(NOTEBOOKS)}})
        client.execute()
    images = out_dir / f"{path.stem}_files"
    shutil.rmtree(images, ignore_errors=True)
    page = out_dir / f"{path.stem}.md"
    page.write_text(markdown(path, nb, images))
    return page


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", help="notebooks to render (default: every one)")
    ap.add_argument("--quick", action="store_true", help="GPGUIDED_NOTEBOOK_QUICK=1 (a check)")
    ap.add_argument("--out", default=str(PAGES), help="where the pages go")
    args = ap.parse_args(argv)
    chosen = [p for p in notebooks() if not args.names or any(p.stem.startswith(n) for n in args.names)]
    if not chosen:
        print(f"no notebook matches {args.names}", file=sys.stderr)
        return 2
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for path in chosen:
        print(f"{path.name} ...", flush=True)
        print(f"wrote {render(path, out, args.quick)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
