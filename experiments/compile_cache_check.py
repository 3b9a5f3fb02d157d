"""Does JAX's persistent compilation cache work on this CPU with the pinned jax? Each program is
compiled in a fresh process with an empty cache directory, then loaded from that cache by a second
fresh process (what a repeated `gpguided reproduce` does); the second process's exit status,
compile-or-load time and JAX's count of programs loaded from the cache are recorded (XLA:CPU
logs a warning about "+prefer-no-gather" on every load on some CPUs, openxla/xla#44565, and
elsewhere rejects the load and compiles again: `loads` needs the count, not only exit 0).

Two kinds of program:

* the chunk program of every preset and method, for one seed (`train.make_train(cfg).run_chunk`
  over 50 updates, without the split over devices), and the three GP methods' shared program
  (`train.make_gp_methods_train`, "gp_methods": the chunk `gpguided reproduce` compiles for them
  by default), with its number of XLA kernels (fusions, dots, custom calls; copies not counted);
* a synthetic program of N unrolled steps (x <- sin(x) @ x^T + i, 8 x 8), a stand-in for a larger
  program than the project ships: with jax 0.9.2 the second process crashes (SIGSEGV, a runaway
  recursion in XLA:CPU's object loader while it resolves the cached program's symbols) from a
  size between N = 200 and 300 on; a larger thread stack does not help.

Prints JSON (--out also writes it).

Usage:
  python experiments/compile_cache_check.py --out docs/results/compile_cache.json
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile

CHILD = r"""
import re, sys, time
import jax
import jax.monitoring
hits = []  # JAX's own event for a program loaded from the persistent cache
jax.monitoring.register_event_listener(
    lambda event, **kw: hits.append(1) if event == "/jax/compilation_cache/cache_hits" else None)
jax.config.update("jax_compilation_cache_dir", sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
import gpguided_jax
gpguided_jax.enable_x64()
import jax.numpy as jnp
kind = sys.argv[2]
if kind == "synthetic":
    n = int(sys.argv[3])
    def f(x):
        for i in range(n):
            x = jnp.sin(x) @ x.T + i
        return x
    lowered = jax.jit(f).lower(jnp.ones((8, 8)))
else:
    from gpguided_jax import config as config_lib, train as train_lib
    gp_methods = sys.argv[4] == "gp_methods"  # the GP methods' shared program (reproduce's default)
    cfg = config_lib.preset(sys.argv[3], method="gp_pg" if gp_methods else sys.argv[4])
    tr = train_lib.make_train(cfg)
    state = jax.eval_shape(lambda k: tr.init(k, cfg, None), jax.random.PRNGKey(0))
    if gp_methods:
        shared = train_lib.make_gp_methods_train(cfg)
        lowered = jax.jit(lambda s, i, c: shared(s, i, c, 50)).lower(
            state, jnp.int32(0), train_lib.gp_methods_key(cfg))
    else:
        lowered = jax.jit(lambda s: tr.run_chunk(s, cfg, 50)).lower(state)
t0 = time.perf_counter()
compiled = lowered.compile()
seconds = time.perf_counter() - t0
text = compiled.as_text()
kernels = len(re.findall(r"= [^ ]+ (?:fusion|dot|custom-call)\(", text))
print("RESULT", seconds, kernels, len(hits), flush=True)
"""


def _child(cache: str, *args: str) -> dict:
    proc = subprocess.run([sys.executable, "-c", CHILD, cache, *args], capture_output=True,
                          text=True, timeout=900)
    found = re.search(r"RESULT ([\d.e+-]+) (\d+) (\d+)", proc.stdout)
    out = {"returncode": proc.returncode}
    if found:
        out.update(seconds=float(found.group(1)), kernels=int(found.group(2)),
                   cache_hits=int(found.group(3)))
    return out


def round_trip(*args: str) -> dict:
    """Compiles in one process (empty cache), loads in a second (the cache it filled). It loads
    if both exit 0 and JAX counts the second's program as loaded from the cache: a load that XLA
    rejected would compile the program again and still exit 0 (jax-ml/jax#38445)."""
    with tempfile.TemporaryDirectory() as cache:
        cold = _child(cache, *args)
        warm = _child(cache, *args)
    return {"cold": cold, "warm": warm,
            "loads": cold["returncode"] == 0 and warm["returncode"] == 0
            and warm.get("cache_hits", 0) > 0}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", nargs="+", default=["paper", "swingup"])
    ap.add_argument("--methods", nargs="+",
                    default=["reinforce", "gp_pg", "guided_variance", "guided_direction",
                             "gp_methods"],
                    help="methods, or gp_methods: the GP methods' shared program")
    ap.add_argument("--synthetic", type=int, nargs="*", default=[100, 200, 300])
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    import jax

    from gpguided_jax import bench

    report = {"jax": jax.__version__, "cpu_count": os.cpu_count(), "programs": [], "synthetic": []}
    for preset in args.presets:
        for method in args.methods:
            row = {"preset": preset, "method": method, **round_trip("chunk", preset, method)}
            report["programs"].append(row)
            print(f"{preset} {method}: {row['cold'].get('kernels')} kernels, loads {row['loads']}",
                  file=sys.stderr, flush=True)
    for n in args.synthetic:
        row = {"steps": n, **round_trip("synthetic", str(n))}
        report["synthetic"].append(row)
        print(f"synthetic {n}: {row['cold'].get('kernels')} kernels, loads {row['loads']} "
              f"(second process exit {row['warm']['returncode']})", file=sys.stderr, flush=True)
    report["all_shipped_programs_load"] = all(r["loads"] for r in report["programs"])
    bench.print_report(report, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
