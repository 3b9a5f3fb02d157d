"""A run's report: `index.html` beside the files `gpguided reproduce` writes, to read in a browser.

`write_report(out_dir)` reads what the run left in `out_dir` (config.json, summary.csv,
comparisons.csv and the PNG figures) and writes one HTML file that needs nothing else: the
figures by relative links (the directory can be moved or copied whole), the summary and
comparison tables, and the run's config (the run's settings, then each method's config, the
fields in which the methods differ first). `reproduce` writes it after its results; for a run
written before, or by hand:

  python -m gpguided_jax.report results/paper
"""

from __future__ import annotations

import csv
import glob
import html
import json
import math
import os
import sys

from gpguided_jax import checkpoints

_STYLE = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 2rem auto;
       max-width: 1200px; padding: 0 1rem; color: #1f2328; line-height: 1.45; }
h1 { font-size: 1.6rem; margin-bottom: 0.2rem; } h2 { font-size: 1.25rem; margin-top: 2rem;
     border-bottom: 1px solid #d0d7de; padding-bottom: 0.2rem; }
p.meta { color: #59636e; margin-top: 0; }
.scroll { overflow-x: auto; }
table { border-collapse: collapse; font-size: 0.85rem; margin: 0.5rem 0 1rem; }
th, td { border: 1px solid #d0d7de; padding: 0.25rem 0.5rem; text-align: left; white-space: nowrap; }
th { background: #f6f8fa; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
tr.differs td { background: #fff8c5; }
table.config td { white-space: normal; max-width: 18rem; overflow-wrap: anywhere; }
table.config td:first-child { white-space: nowrap; max-width: none; }  /* the field's name */
figure { margin: 1rem 0; } figure img { max-width: 100%; border: 1px solid #d0d7de; }
figcaption { color: #59636e; font-size: 0.9rem; }
code { background: #f6f8fa; padding: 0.1rem 0.3rem; border-radius: 4px; }
"""


# the figures `reproduce` writes, in the order to show them, with their captions; any other PNG of
# the directory follows, under its file name
FIGURES = {"fig5_reward.png": "Fig. 5a: the learning episodes' mean reward per step, mean and 95% "
                              "interval over the seeds",
           "fig5_exploration.png": "Fig. 5b: the exploration's standard deviation over the visited "
                                   "states, mean and 95% interval over the seeds"}


def _td(text: str) -> str:
    """A table cell, numbers aligned right."""
    try:
        float(text)
    except ValueError:
        return f"<td>{html.escape(text)}</td>"
    return f'<td class="num">{html.escape(text)}</td>'


def _cell(value: str) -> str:
    """A CSV cell as shown: numbers to 4 significant digits (integers as they are)."""
    try:
        x = float(value)
    except ValueError:
        return _td(value)
    if math.isnan(x) or math.isinf(x) or x == int(x) and abs(x) < 1e15 and "." not in value:
        return _td(value)
    return _td(f"{x:.4g}")


def _csv_table(path: str) -> str:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        return "<p>(empty)</p>"
    head = "".join(f"<th>{html.escape(h)}</th>" for h in rows[0])
    body = "\n".join("<tr>" + "".join(_cell(v) for v in r) + "</tr>" for r in rows[1:])
    return f'<div class="scroll"><table>\n<tr>{head}</tr>\n{body}\n</table></div>'


def _value(v) -> str:
    """A config value as shown: floats to 6 significant digits, also inside lists and dicts."""
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_value(x)}" for k, x in v.items()) + "}"
    return str(v)


def _config_tables(config: dict) -> str:
    """The run's own settings, then a field x method table of the methods' configs (the fields in
    which they differ first, highlighted)."""
    run = {k: v for k, v in config.items() if k != "methods"}
    if isinstance(run.get("seeds"), list) and len(run["seeds"]) > 6:
        s = run["seeds"]
        run["seeds"] = f"{len(s)} seeds, {s[0]}–{s[-1]}" if s == list(range(s[0], s[-1] + 1)) else s
    parts = ['<div class="scroll"><table>']
    parts += [f"<tr><th>{html.escape(k)}</th>{_td(_value(v))}</tr>" for k, v in run.items()]
    parts.append("</table></div>")
    methods = config.get("methods", {})
    if methods:
        names = list(methods)
        fields = list(dict.fromkeys(f for m in names for f in methods[m]))
        differs = [f for f in fields if len({_value(methods[m].get(f, "–")) for m in names}) > 1]
        same = [f for f in fields if f not in differs]
        head = "".join(f"<th>{html.escape(m)}</th>" for m in names)
        parts.append(f'<div class="scroll"><table class="config">\n<tr><th>field</th>{head}</tr>')
        for f in differs + same:
            cls = ' class="differs"' if f in differs else ""
            cells = "".join(_td(_value(methods[m].get(f, "–"))) for m in names)
            parts.append(f"<tr{cls}><td>{html.escape(f)}</td>{cells}</tr>")
        parts.append("</table></div>")
    return "\n".join(parts)


def _title(config: dict) -> str:
    methods = config.get("methods", {})
    envs = sorted({str(c.get("env", "pendulum")) for c in methods.values()}) or ["?"]
    return f"gpguided reproduce: preset {config.get('preset', '?')}, {', '.join(envs)}"


def render(out_dir: str) -> str:
    """The report of the run in `out_dir` as one HTML document (module notes)."""
    with open(os.path.join(out_dir, "config.json")) as f:
        config = json.load(f)
    title = html.escape(_title(config))
    seeds = config.get("seeds", [])
    methods = list(config.get("methods", {}))
    parts = ["<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">',
             '<meta name="viewport" content="width=device-width, initial-scale=1">',
             f"<title>{title}</title>", f"<style>{_STYLE}</style>", "</head>", "<body>",
             f"<h1>{title}</h1>",
             f'<p class="meta">{len(methods)} method{"s" if len(methods) != 1 else ""} '
             f"({html.escape(', '.join(methods))}), {len(seeds)} seed"
             f"{'s' if len(seeds) != 1 else ''}, {html.escape(str(config.get('dtype', '')))}. "
             "The files of the run are beside this page: <code>results.npz</code> (every "
             "record per method, seed and update), <code>summary.csv</code>, "
             "<code>comparisons.csv</code> and <code>config.json</code>.</p>"]
    names = sorted(os.path.basename(p) for p in glob.glob(os.path.join(out_dir, "*.png")))
    names = [n for n in FIGURES if n in names] + [n for n in names if n not in FIGURES]
    if names:
        parts.append("<h2>Figures</h2>")
        for name in names:
            caption = html.escape(FIGURES.get(name, name))
            parts.append(f'<figure><img src="{html.escape(name)}" alt="{caption}">'
                         f"<figcaption>{caption} (<code>{html.escape(name)}</code>)</figcaption>"
                         "</figure>")
    for name, heading in (("summary.csv", "Summary"),
                          ("comparisons.csv", "Probability of improvement")):
        path = os.path.join(out_dir, name)
        if os.path.exists(path):
            parts += [f"<h2>{heading} <small>(<code>{name}</code>)</small></h2>", _csv_table(path)]
    parts += ["<h2>Config <small>(<code>config.json</code>)</small></h2>", _config_tables(config),
              "</body>", "</html>", ""]
    return "\n".join(parts)


def write_report(out_dir: str) -> str:
    """Writes `out_dir/index.html` (atomically) and returns its path."""
    path = os.path.join(out_dir, "index.html")
    checkpoints.atomic_write_text(path, render(out_dir))
    return path


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or args[0].startswith("-"):
        print("usage: python -m gpguided_jax.report RUN_DIR", file=sys.stderr)
        return 2
    if not os.path.exists(os.path.join(args[0], "config.json")):
        print(f"gpguided_jax.report: error: no config.json in {args[0]}", file=sys.stderr)
        return 1
    print(f"wrote {write_report(args[0])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
